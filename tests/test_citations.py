"""Citations: every repository path, module and documentation section that the repository's
own text names exists.

A user's clone holds only this repository, so a comment, docstring, doc, benchmark note, scene
or kernel that sends the reader somewhere must send them to a place that is there:

* a path token whose first folder is one of the repository's top-level folders
  (``optics/transmittance.py``, ``bench/results/gather.json``, ``docs/science.md``,
  ``scenes/layers/``) names a file or folder of the tree; a ``.py`` path under ``dermis/``
  names one too, and any other ``.py`` path must belong to an installed package
  (``distributed/worker_state_machine.py``), so a dissolved folder cannot hide;
* a dotted name ``dermis.pkg.module[.name]`` names a module of the tree and, where it goes on,
  a name that module defines at top level;
* a documentation section cited by name (``docs/software.md "Cache keys"``, ``science.md §4
  "Near field"``) is a heading, or the bold lead-in of a paragraph, of that document; a
  ``§N`` is a numbered section of docs/science.md; an anchor (``science.md#conventions``)
  is the GitHub slug of one of its headings; a relative Markdown link resolves;
* nothing points outside the repository (the design notes).

Placeholders (``cl/<file>``, ``scenes/layers/*.toml``) are not paths and are not checked, nor
are examples in the fenced code blocks of Markdown files (what a user may add, such as a new
model's module).
"""
from __future__ import annotations

import ast
import functools
import importlib.util
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SELF = "tests/test_citations.py"      # its examples of broken citations are not citations
MAX_BYTES = 4_000_000                 # larger tracked files are data (meshes, maps), not text


def _files() -> list[str]:
    """Tracked files plus new ones git does not ignore (what a commit of the tree would hold)."""
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout: the tracked files are unknown")
    out = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout
    return sorted({f for f in out.splitlines() if f and (REPO / f).is_file()})


def _texts() -> dict[str, str]:
    texts = {}
    for name in _files():
        path = REPO / name
        if path.stat().st_size > MAX_BYTES:
            continue
        data = path.read_bytes()
        if b"\0" in data:
            continue
        try:
            texts[name] = data.decode("utf-8")
        except UnicodeDecodeError:
            continue
    return texts


def _top_folders(names) -> list[str]:
    return sorted({n.split("/")[0] for n in names if "/" in n})


def _path_pattern(tops) -> re.Pattern:
    # <top>/<folders>/<name>.<ext>, or <top>/<folders>/ (a folder); not inside a longer path or
    # URL, and not a placeholder (<...>) or a glob (*)
    alt = "|".join(map(re.escape, tops))
    return re.compile(rf"(?<![\w./\\-])((?:{alt})/(?:[\w.\-]+/)*(?:[\w\-]+\.[A-Za-z0-9]+)?)"
                      r"(?![\w*<>/-])")


OTHER_PY = re.compile(r"(?<![\w./\\:-])([A-Za-z_]\w*)/((?:[\w\-]+/)*[\w\-]+\.py)(?![\w*<>/-])")
DOTTED = re.compile(r"(?<![\w./-])dermis((?:\.[A-Za-z_]\w*)+)(?![\w-])")
DOC = r"(?:docs/)?(%s)\.md" % "|".join(sorted(re.escape(p.stem)
                                              for p in (REPO / "docs").glob("*.md")))
SECTION = re.compile(DOC + r"(?:,?\s*§(\d+))?(?:(?:,\s*|\s+\(?)\"([^\"\n]{1,80})\")?")
ANCHOR = re.compile(DOC + r"#([\w-]+)")
LINK = re.compile(r"\]\(([^)\s#]*)(?:#([\w-]+))?\)")


def _line(text: str, pos: int) -> int:
    return text.count("\n", 0, pos) + 1


def _plain(heading: str) -> str:
    """A heading or bold lead-in as a reader cites it: no markup, no ``§N``, case-folded."""
    heading = re.sub(r"^§\d+\s*", "", heading.replace("`", "").replace("*", "").strip())
    return heading.casefold()


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@functools.cache
def _doc(name: str):
    """(headings, bold lead-ins, anchors, numbered sections) of docs/<name>."""
    path = REPO / "docs" / name
    if not path.is_file():
        return None
    text = path.read_text()
    heads = re.findall(r"^#+ (.+)$", text, re.M)
    bold = re.findall(r"\*\*([^*\n]+?)\.?\*\*", text)
    numbered = set(re.findall(r"^## §(\d+)", text, re.M))
    return ([_plain(h) for h in heads], [_plain(b) for b in bold],
            {_slug(h) for h in heads}, numbered)


def _section_ok(doc: str, cited: str) -> bool:
    heads, bold, _, _ = _doc(doc)
    cited = _plain(cited)
    return any(h.startswith(cited) for h in heads + bold)


@functools.cache
def _defined(module: Path) -> frozenset:
    """Top-level names a module binds (defs, classes, assignments, imports)."""
    names = set()
    for node in ast.parse(module.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return frozenset(names)


def _dotted_ok(parts: list[str]) -> bool:
    path = REPO
    for part in parts:
        if part.startswith("__") and part.endswith("__"):
            return True                               # dermis.__file__, __version__, ...
        if path.is_dir() and (path / part).is_dir():
            path = path / part                        # a package or a data folder
        elif path.is_dir() and (path / f"{part}.py").is_file():
            path = path / f"{part}.py"
        else:
            module = path / "__init__.py" if path.is_dir() else path
            return module.is_file() and part in _defined(module)
    return True


@functools.cache
def _installed(top: str) -> bool:
    try:
        return importlib.util.find_spec(top) is not None
    except (ImportError, ValueError):
        return False


def _unfenced(text: str) -> str:
    """Markdown text with its fenced code blocks blanked (lines kept): an example there shows
    what a user may write (a new model's module), not where something is."""
    return re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), text,
                  flags=re.M | re.S)


def _broken(name: str, text: str, path_re: re.Pattern, tops) -> list[str]:
    bad = []
    if name.endswith(".md"):
        text = _unfenced(text)
    where = lambda m: f"{name}:{_line(text, m.start())}"   # noqa: E731
    for m in path_re.finditer(text):
        token = m.group(1)
        if not (REPO / token).exists():
            bad.append(f"{where(m)}: {token} does not exist")
    for m in OTHER_PY.finditer(text):
        top, rest = m.groups()
        if top in tops:
            continue
        if top == "dermis":
            if not (REPO / rest).is_file():
                bad.append(f"{where(m)}: dermis/{rest} does not exist")
        elif not _installed(top):
            bad.append(f"{where(m)}: {top}/{rest}: no folder {top}/ here, no package {top}")
    for m in DOTTED.finditer(text):
        if not _dotted_ok(m.group(1).strip(".").split(".")):
            bad.append(f"{where(m)}: dermis{m.group(1)} is no module or name of the tree")
    for m in SECTION.finditer(text):
        doc, number, section = m.group(1) + ".md", m.group(2), m.group(3)
        if not m.group(0).startswith("docs/") and doc == "README.md":
            continue                                  # the top-level or a data folder's README
        if _doc(doc) is None:
            if m.group(0).startswith("docs/"):
                bad.append(f"{where(m)}: docs/{doc} does not exist")
            continue
        if number and number not in _doc(doc)[3]:
            bad.append(f"{where(m)}: docs/{doc} has no §{number}")
        if section and not _section_ok(doc, section):
            bad.append(f"{where(m)}: docs/{doc} has no section {section!r}")
    for m in ANCHOR.finditer(text):
        doc = m.group(1) + ".md"
        if _doc(doc) is not None and m.group(2) not in _doc(doc)[2]:
            bad.append(f"{where(m)}: docs/{doc} has no anchor #{m.group(2)}")
    if name.endswith(".md"):
        for m in LINK.finditer(text):
            target, anchor = m.groups()
            if target.startswith(("http:", "https:", "mailto:")) or not (target or anchor):
                continue
            path = ((REPO / name).parent / target).resolve() if target else REPO / name
            if not path.exists():
                bad.append(f"{where(m)}: link {target} does not resolve")
            elif anchor and path.suffix == ".md" and path.parent == REPO / "docs" and \
                    anchor not in _doc(path.name)[2]:
                bad.append(f"{where(m)}: link {target}#{anchor}: no such heading")
    # the paths spelled in pieces, so this guard does not cite them itself
    for outside in ("shared/" "design", "/work" "/shared"):
        if outside in text:
            bad.append(f"{name}: cites {outside!r}, outside the repository")
    return bad


def test01_every_cited_path_module_and_section_exists():
    texts = _texts()
    tops = _top_folders(texts)
    assert {"docs", "pipeline", "stages", "tests"} <= set(tops), tops
    path_re = _path_pattern(tops)
    bad = [b for name, text in texts.items() if name != SELF
           for b in _broken(name, text, path_re, tops)]
    assert not bad, "\n".join(bad)


def test02_the_checks_catch_what_they_are_for():
    tops = ["docs", "optics", "stages"]
    path_re = _path_pattern(tops)
    cases = {
        "optics/transmittance.py": 0, "stages/nowhere.py": 1, "cl/<file>": 0,
        "scenes/layers/*.toml": 0, "physics/lights.py": 1, "dermis/optics/fresnel.py": 0,
        "distributed/worker_state_machine.py": 0, "dermis.optics.transmittance": 0,
        "dermis.physics": 1, "dermis.pipeline.registry.model": 0,
        "dermis.pipeline.registry.nothing": 1, 'docs/software.md "Cache keys"': 0,
        'docs/software.md "No such section"': 1, "docs/science.md §4 \"Near field\"": 0,
        "docs/science.md §9": 1, "science.md#conventions": 0, "science.md#nowhere": 1,
        "docs/nowhere.md": 1, 'README.md ("Any")': 0, "/work" "/shared/x.md": 1,
        "`stages/nowhere.py`": 1,
    }
    for text, n in cases.items():
        assert len(_broken("x.py", f"see {text} here", path_re, tops)) == n, text
    fenced = "see stages/nowhere.py\n```python\n# models/grey.py\n```\n"
    assert len(_broken("x.md", fenced, path_re, tops)) == 1


# What a reader of the repository cannot look up: the tracker's numbers and the history of
# the work (git log holds it).  Spelled in pieces so that this file does not match itself.
JOURNAL = re.compile(r"\b(?:" + "iss" + r"ue ?#?\d+|ses" + r"sion \d+|the le" + r"ad\b|the bri"
                     + r"ef\b)", re.IGNORECASE)


def test03_the_repository_speaks_of_the_product():
    found = [f"{name}:{_line(text, m.start())}: {m.group(0)!r}"
             for name, text in _texts().items() for m in JOURNAL.finditer(text)]
    assert not found, "\n".join(found)
    word = bytes([105, 115, 115, 117, 101]).decode()     # the tracker's word, not spelled here
    assert JOURNAL.search(f"as {word} {6 * 2} asked") and not JOURNAL.search(f"t{word} {6 * 2}")
