"""``python -m delayed_ilqr_entry``: the ``delayed-ilqr`` command, as the console script runs it."""
from . import main

main()
