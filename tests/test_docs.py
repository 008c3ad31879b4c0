"""The documentation runs: every fenced Python block and every shell command of the README, and
every docstring example (``>>>``) of the packages, is executed here, so the docs cannot drift
from the code.

* README ```python blocks run in document order, each in a fresh namespace, in one scratch
  directory that holds a link to ``scenes/`` (so paths read as from the repository root), and
  must finish without an exception. The blocks of the other documents in ``OTHER_READMES``
  (``scenes/README.md`` and the pages of ``docs/``) run after them by the same rules, in that
  list's order and in the same directory: a page's block may use a file that a README block
  wrote (a heavy block only one that a heavy block wrote).
* README ```bash blocks run in the same directory, one command at a time (``\\`` continues a
  line), and must exit 0. The installation steps (``python -m pip install ...``) and the test
  suite itself (``python -m pytest``) are what CI runs around this test, so they are skipped.
* A block whose fence is preceded by the line ``<!-- test: slow -->`` runs only with
  ``pytest -m slow``; ``<!-- test: heavy -->`` runs in CI's second tier (``pytest -m heavy``, for
  blocks that compile many programs; a heavy block may use files only from heavy blocks above it); ``<!-- test: skip REASON -->`` never runs (the reason must be given).
  ```text blocks are not code (command syntax, file layouts).
* Docstring examples: :mod:`doctest` on every module of ``jaxplush`` (``jaxplush.fitting`` included); a
  docstring must not hide an example in a reST literal block (``::``), which doctest would skip.
"""

from __future__ import annotations

import doctest
import importlib
import importlib.util
import os
import pkgutil
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
BIN = Path(sys.executable).parent

_FENCE = re.compile(r"^```(\w*)\s*$")
_MARK = re.compile(r"^<!--\s*test:\s*(slow|heavy|skip)\b(.*?)-->\s*$")


def blocks(path=README):
    """(line, language, code, mark) of every fenced block; mark is None, "slow", "heavy" or "skip"."""
    lines = Path(path).read_text().splitlines()
    out = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if m and m.group(1):
            lang, start = m.group(1), i + 1
            j = start
            while j < len(lines) and lines[j].strip() != "```":
                j += 1
            mark = None
            prev = lines[i - 1].strip() if i > 0 else ""
            mm = _MARK.match(prev)
            if mm:
                mark = mm.group(1)
                assert mark != "skip" or mm.group(2).strip(), f"{path}:{i}: a skip mark needs a reason"
            out.append((start, lang, "\n".join(lines[start:j]), mark))
            i = j + 1
        else:
            i += 1
    return out


def shell_commands(code):
    """The commands of a bash block: continuation lines joined, comments and blank lines dropped,
    installation and test-suite steps of ``&&`` chains removed."""
    joined = re.sub(r"\\\n\s*", " ", code)
    out = []
    for line in joined.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split("&&")]
        parts = [p for p in parts if not re.match(r"python3? -m (pip install|pytest)\b", p)]
        if parts:
            out.append(" && ".join(parts))
    return out


def _strip_comment(cmd):
    """Drop a trailing shell comment (outside quotes); a command without ``#`` runs as written
    (loops, ``&`` and ``$VARIABLES`` intact)."""
    if "#" not in cmd:
        return cmd
    lexer = shlex.shlex(cmd, posix=True, punctuation_chars=False)
    lexer.commenters = "#"
    lexer.whitespace_split = True
    return " ".join(shlex.quote(t) if t != "&&" else t for t in lexer)


README_BLOCKS = [b for b in blocks() if b[1] in ("python", "bash", "sh")]
#: Other documents whose blocks run too (the same rules; paths relative to the repository root).
OTHER_READMES = ("scenes/README.md", "docs/cli.md", "docs/scenes.md", "docs/contact.md", "docs/simulation.md",
                 "docs/api.md", "docs/fitting.md", "docs/sweeps.md", "docs/development.md", "docs/formats.md",
                 "docs/viewer.md")
#: Blocks that use the viewer need its optional extra (viser; the test extra includes it).
_VIEWER = re.compile(r"\bjaxplush view\b|\bio\.view\(")
HAVE_VISER = importlib.util.find_spec("viser") is not None
#: The README is a front page: longer text belongs in docs/.
README_MAX_LINES = 300
#: The quick start's two commands, verbatim: CI (.ci/run) runs the second one.
QUICK_START = (
    "python -m pip install -e . && jaxplush simulate scenes/ball_drop.obj --steps 16000 --dt 1.25e-4 "
    "--save-every 80 --out ball_drop.h5",
    'python -m pip install -e ".[test]" && python -m pytest -q',
)


def _param(b, doc="README.md"):
    line, lang, code, mark = b
    marks = [getattr(pytest.mark, mark)] if mark in ("slow", "heavy") else []
    if mark == "skip":
        marks.append(pytest.mark.skip(reason=f"marked skip in {doc}"))
    if not HAVE_VISER and _VIEWER.search(code):
        marks.append(pytest.mark.skip(reason='needs the viewer extra: pip install -e ".[viewer]"'))
    return pytest.param((doc,) + b, id=f"{doc}:{line}-{lang}", marks=marks)


ALL_BLOCKS = [_param(b) for b in README_BLOCKS] + [
    _param(b, doc) for doc in OTHER_READMES for b in blocks(ROOT / doc) if b[1] in ("python", "bash", "sh")]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("readme")
    (d / "scenes").symlink_to(ROOT / "scenes")
    return d


def test_readme_has_runnable_blocks():
    langs = [b[1] for b in README_BLOCKS]
    assert langs.count("python") >= 3 and langs.count("bash") >= 3
    # every command-looking line is in a runnable block, not a text block
    for doc in ("README.md",) + OTHER_READMES:
        for line, lang, code, _ in blocks(ROOT / doc):
            if lang == "text":
                assert not re.search(r"^\s*(jaxplush|jaxplush-fit|python) ", code, re.M) or "SCENE" in code \
                    or "[" in code, f"{doc}:{line}: a text block holds a command; make it a bash block or a syntax line"


def test_readme_is_a_front_page():
    """The README stays short (the rest is in docs/), its quick start holds the two commands that
    CI and newcomers run, verbatim, and it shows a simulate, a fit and a sweep example."""
    text = README.read_text()
    n = len(text.splitlines())
    assert n < README_MAX_LINES, f"README.md has {n} lines; move detail to a page in docs/"
    quick = next(code for _, lang, code, _ in blocks() if lang == "bash")
    for cmd in QUICK_START:
        assert cmd in quick.splitlines(), f"the quick start's first block lacks `{cmd}`"
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python -m pytest -q" in ci and '".[test]"' in ci
    codes = "\n".join(code for _, _, code, _ in README_BLOCKS)
    for needle in ("jaxplush simulate", "jaxplush.simulate(", "jaxplush-fit ", "fitting.fit(",
                   "jaxplush-fit sweep", "sweep("):
        assert needle in codes, f"README.md has no runnable example using {needle!r}"


def test_every_docs_page_with_code_runs():
    """A page of docs/ with a python or bash block is in OTHER_READMES, so its blocks run."""
    for page in sorted((ROOT / "docs").glob("*.md")):
        rel = page.relative_to(ROOT).as_posix()
        if any(b[1] in ("python", "bash", "sh") for b in blocks(page)):
            assert rel in OTHER_READMES, f"{rel} has runnable blocks: add it to OTHER_READMES"


def _slug(heading):
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip())    # a link's text only
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def _anchors(path):
    """Every anchor of a Markdown file: its headings (duplicates numbered) and HTML ids."""
    seen, out = {}, set()
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.M | re.S)
    for m in re.finditer(r"^#{1,6}\s+(.*?)\s*#*\s*$", text, re.M):
        slug = _slug(m.group(1))
        out.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    out |= set(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", text))
    return out


LINKED_DOCS = ("README.md", "ARCHITECTURE.md", "scenes/README.md") + tuple(
    sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").glob("*.md"))) + tuple(
    sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "notebooks").glob("*.ipynb")))


def _markdown(path):
    """The Markdown of a document: the file, or a notebook's Markdown cells."""
    if path.suffix != ".ipynb":
        return path.read_text()
    import json
    cells = json.loads(path.read_text())["cells"]
    return "\n\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")


@pytest.mark.parametrize("doc", LINKED_DOCS)
def test_relative_links_resolve(doc):
    """Every relative link (and image) of the README, the docs and the notebooks points at a file
    that exists, and a ``#anchor`` at a heading of that file."""
    path = ROOT / doc
    text = re.sub(r"^```.*?^```", "", _markdown(path), flags=re.M | re.S)   # not in code blocks
    text = re.sub(r"``.+?``|`[^`\n]*`", "", text)                             # nor in code spans
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):                           # http:, mailto:, ...
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target}: no heading with that anchor in {dest.relative_to(ROOT)}")
    assert not bad, f"{doc}: broken links:\n" + "\n".join(bad)


@pytest.mark.parametrize("block", ALL_BLOCKS)
def test_readme_block_runs(block, workdir, monkeypatch):
    doc, line, lang, code, _ = block
    monkeypatch.chdir(workdir)
    if lang == "python":
        import matplotlib
        matplotlib.use("Agg")
        namespace = {"__name__": "__readme__"}
        exec(compile(code, f"{doc}:{line}", "exec"), namespace)   # noqa: S102
        return
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", JAXPLUSH_TEST="1")
    for cmd in shell_commands(code):
        run = _strip_comment(cmd).replace("python ", f"{shlex.quote(sys.executable)} ", 1) \
            if cmd.startswith("python ") else _strip_comment(cmd)
        proc = subprocess.run(["bash", "-c", run], cwd=workdir, env=env, capture_output=True, text=True,
                              timeout=900)
        assert proc.returncode == 0, (f"{doc}:{line}: `{cmd}` exited {proc.returncode}\n"
                                      f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}")


def _modules():
    """Every module of jaxplush, its subpackages and jaxplush.fitting."""
    import jaxplush
    import jaxplush.fitting                      # installed from fitting/ (not under jaxplush/'s path)
    names = {"jaxplush", "jaxplush.fitting"}
    for pkg in (jaxplush, jaxplush.fitting):
        names |= {m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")}
    return sorted(n for n in names if not n.endswith("__main__"))


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples_run(name, monkeypatch):
    monkeypatch.chdir(ROOT)
    module = importlib.import_module(name)
    tests = doctest.DocTestFinder(exclude_empty=False).find(module, name)
    for t in tests:
        # an example must be a doctest, not a reST literal block that doctest would skip
        assert not re.search(r"::\s*$", t.docstring or "", re.M), \
            f"{name}: the docstring of {t.name} holds a '::' literal block; write examples as doctests (>>>)"
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for t in tests:
        if t.examples:
            runner.run(t)
    res = runner.summarize(verbose=False)
    assert res.failed == 0, f"{name}: {res.failed} docstring example(s) failed (output above)"
