"""The documentation site (mkdocs.yml, docs/): it builds in strict mode (no broken reference, no
docstring that documents a parameter the signature lacks), and every Python example of the home
page and the guide runs, page by page in one namespace, as a reader would paste it."""
import contextlib
import io
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).parents[1]
DOCS = ROOT / "docs"
PAGES = ["index.md"] + sorted(str(p.relative_to(DOCS)) for p in (DOCS / "guide").glob("*.md"))
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def test_site_builds_strict(tmp_path):
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                             str(ROOT / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
                            cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-5000:]
    for page in ["index.html", "guide/time/index.html", "guide/saving/index.html", "api/solver/index.html",
                 "derivation/index.html"]:
        assert (tmp_path / "site" / page).is_file(), page
    api = (tmp_path / "site" / "api" / "solver" / "index.html").read_text()
    assert "time_dependent" in api and "delayed_ilqr.saving" in api     # rendered from the docstrings


def test_every_guide_page_is_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    assert all(page in nav for page in PAGES)


@pytest.mark.parametrize("page", PAGES)
def test_page_examples_run(page):
    blocks = BLOCK.findall((DOCS / page).read_text())
    if page != "index.md":
        assert blocks, f"{page} has no Python example"
    namespace = {"__name__": f"docs_{page}"}
    for j, code in enumerate(blocks):
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(code, f"docs/{page} (python block {j + 1})", "exec"), namespace)
