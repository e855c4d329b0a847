"""``python -m delayed_ilqr.cli``: the ``delayed-ilqr`` command."""
from . import main

main()
