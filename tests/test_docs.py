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
# the pages whose examples compile several large programs (the six-muscle arm, receding horizon,
# sensors with their filter, bounded solves): run by `make bench` (pytest -m full); every other
# page runs in the suite, and each of these pages' APIs has its own tests
HEAVY_PAGES = {"guide/sensors.md", "guide/limits.md", "guide/mpc.md", "guide/statistics.md"}
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
    # the notation table is a table, and the cross-references are links, not raw text
    assert re.search(r"<th>symbol</th>\s*<th>meaning</th>", api)
    for page in (tmp_path / "site" / "api").rglob("*.html"):
        html = page.read_text()
        assert not SPHINX_ROLE.search(html) and "[<code>" not in html, page
        assert "autorefs-internal" in html, page


def test_every_guide_page_is_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    assert all(page in nav for page in PAGES)


@pytest.mark.parametrize("page", [pytest.param(p, marks=pytest.mark.full) if p in HEAVY_PAGES else p for p in PAGES])
def test_page_examples_run(page):
    blocks = BLOCK.findall((DOCS / page).read_text())
    if page != "index.md":
        assert blocks, f"{page} has no Python example"
    namespace = {"__name__": f"docs_{page}"}
    for j, code in enumerate(blocks):
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(code, f"docs/{page} (python block {j + 1})", "exec"), namespace)


# ---------------------------------------------------------------------------------------------
# the API reference: one docstring style, every public name

SRC = ROOT / "src" / "delayed_ilqr"
SPHINX_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|obj|exc|const|ref|any):`")


def _docstrings(path):
    """Every string-expression statement of a module (module, class, function and attribute
    docstrings) and its ``#:`` doc-comments, with line numbers."""
    import ast
    source = path.read_text()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            yield node.lineno, node.value.value
    for k, line in enumerate(source.splitlines(), 1):
        if line.lstrip().startswith("#:"):
            yield k, line


def test_no_sphinx_roles_in_docstrings():
    """mkdocstrings shows reStructuredText roles as raw text: cross-references are written
    [`name`][delayed_ilqr.path] (autorefs) or `name`."""
    found = [f"{path.relative_to(ROOT)}:{line}: {m.group(0)}" for path in sorted(SRC.rglob("*.py"))
             for line, text in _docstrings(path) for m in SPHINX_ROLE.finditer(text)]
    assert not found, "\n".join(found[:20])


def test_no_rst_tables_in_docstrings():
    """reStructuredText simple tables (==== borders) run together on the site: Markdown tables."""
    border = re.compile(r"^\s*=+( +=+)+\s*$", re.M)
    found = [f"{path.relative_to(ROOT)}:{line}" for path in sorted(SRC.rglob("*.py"))
             for line, text in _docstrings(path) if border.search(text)]
    assert not found, found


def _documented_objects():
    """The objects that the API pages render, by id(): each ``::: identifier`` and, for a module
    rendered with its members, the names of its ``__all__``."""
    import importlib
    import types
    objects = set()
    for page in (DOCS / "api").glob("*.md"):
        for ident, options in re.findall(r"^::: *([\w.]+)\n((?:[ \t]+\S.*\n)*)", page.read_text() + "\n", re.M):
            parts = ident.split(".")
            obj = importlib.import_module(parts[0])
            for k, name in enumerate(parts[1:], 2):     # attributes first, as the site resolves them
                obj = getattr(obj, name, None) or importlib.import_module(".".join(parts[:k]))
            objects.add(id(obj))
            if isinstance(obj, types.ModuleType) and not re.search(r"members: *false", options):
                objects.update(id(getattr(obj, name)) for name in getattr(obj, "__all__", ()))
    return objects


@pytest.mark.parametrize("module", ["delayed_ilqr", "delayed_ilqr.lqg", "delayed_ilqr.models"])
def test_reference_lists_every_public_name(module):
    import importlib
    mod = importlib.import_module(module)
    documented = _documented_objects()
    missing = [name for name in mod.__all__ if id(getattr(mod, name)) not in documented]
    assert not missing, f"{module}.__all__ names missing from docs/api/*.md: {missing}"


def test_reference_lists_the_studies():
    import delayed_ilqr.experiments.center_out as center_out
    import delayed_ilqr.experiments.delay_study as delay_study
    documented = _documented_objects()
    assert id(center_out) in documented and id(delay_study) in documented


def test_reference_pages_are_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    missing = [p.name for p in (DOCS / "api").glob("*.md") if f"api/{p.name}" not in nav]
    assert not missing, missing


# ---------------------------------------------------------------------------------------------
# the pages and the README name only what exists

def _markdown_files():
    return [ROOT / "README.md"] + sorted(DOCS.rglob("*.md"))


def _code(text):
    """The code a page shows: fenced blocks and inline code spans."""
    fenced = re.findall(r"^```[^\n]*\n(.*?)^```", text, re.S | re.M)
    rest = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.S | re.M)
    return fenced + re.findall(r"`([^`\n]+)`", rest)


def test_pages_name_only_real_commands_and_options():
    """Every `delayed-ilqr <command> ... --option` that the README and the docs show is a command
    of the command line, and each of its options is one of that command's (or the group's)."""
    import click
    from delayed_ilqr.cli import main

    def options(command):
        return {opt: p for p in command.params if isinstance(p, click.Option) for opt in p.opts + p.secondary_opts}

    group = options(main) | {"--help": None, "-h": None}
    bad, seen = [], 0
    for path in _markdown_files():
        for code in _code(path.read_text()):
            for line in code.replace("\\\n", " ").splitlines():
                for m in re.finditer(r"delayed-ilqr((?: +[^\s|;#`]+)*)", line):
                    words = m.group(1).split()
                    while words and words[0].startswith("-"):      # the group's own options
                        option = group.get(words.pop(0).split("=")[0])
                        if option is not None and not option.is_flag and words:
                            words.pop(0)
                    if not words:
                        continue
                    seen += 1
                    where = f"{path.relative_to(ROOT)}: `{m.group(0).strip()}`"
                    command = main.commands.get(words[0])
                    if command is None:
                        bad.append(f"{where}: no command {words[0]!r}")
                        continue
                    known = group | options(command)
                    bad += [f"{where}: {words[0]} has no {w}" for w in words[1:]
                            if re.fullmatch(r"--?[a-zA-Z][\w-]*(=.*)?", w) and w.split("=")[0] not in known]
    assert seen > 10, seen                              # the scan finds the commands the pages show
    assert not bad, "\n".join(bad)


def test_named_files_exist():
    """Every docs/ page that the README, the docs or a docstring or report names exists, and every
    other .md file named in the code is one the command line writes."""
    bad = []
    for path in _markdown_files() + sorted(SRC.rglob("*.py")):
        text = path.read_text()
        for name in re.findall(r"(?<![\w/.-])(docs/[\w/.-]+\.(?:md|png))", text):
            if not (ROOT / name).is_file():
                bad.append(f"{path.relative_to(ROOT)}: {name}")
    code = "\n".join(p.read_text() for p in SRC.rglob("*.py"))
    for name in set(re.findall(r"(?<![\w/.-])([\w-]+\.md)\b", code)):
        if f'"{name}"' not in code:             # written by the code: (out / "report.md").write_text
            bad.append(f"src: {name} is neither a docs/ page nor a file the command line writes")
    assert not bad, "\n".join(bad)


def test_no_issue_numbers():
    """Code and docs are understood without the project's history."""
    pattern = re.compile(r"\b[Ii]ssues?[ -]#?\d+")
    found = [f"{path.relative_to(ROOT)}:{k}: {line.strip()[:100]}"
             for path in _markdown_files() + sorted(SRC.rglob("*.py")) + sorted((ROOT / "tests").glob("*.py"))
             + sorted((ROOT / "benchmarks").rglob("*.py")) + sorted((ROOT / "benchmarks").glob("*.md"))
             if path != pathlib.Path(__file__)
             for k, line in enumerate(path.read_text().splitlines(), 1) if pattern.search(line)]
    assert not found, "\n".join(found[:30])


def test_tables_stand_apart():
    """A Markdown table directly under a line of text is not a table (it runs into the paragraph):
    every table of the pages and the docstrings has a blank line before it."""
    def run_together(text):
        lines = text.split("\n")
        return [lines[k - 1].strip()[:60] for k in range(1, len(lines))
                if re.match(r"\s*\|.*\|\s*$", lines[k]) and lines[k - 1].strip()
                and not re.match(r"\s*\|", lines[k - 1])]
    bad = [f"{path.relative_to(ROOT)}: {line}" for path in _markdown_files() for line in run_together(path.read_text())]
    bad += [f"{path.relative_to(ROOT)}:{k}: {line}" for path in sorted(SRC.rglob("*.py"))
            for k, text in _docstrings(path) for line in run_together(text)]
    assert not bad, "\n".join(bad)
