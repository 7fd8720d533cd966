"""The documentation runs: every ```python block of README.md and docs/**/*.md executes,
every relative link points to a file that exists, and no source-text file name is cited.

A block is skipped only when the line before its opening fence is ``<!-- no-test -->``.
Each block runs in a fresh namespace with a temporary directory as the working directory.
"""

from __future__ import annotations

import contextlib
import logging
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP_MARK = "<!-- no-test -->"
FENCE = re.compile(r"^```(\w*)\s*$")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
# Written by a generator from the scenario schema, on its own schedule: a link to it is
# checked once the file exists.
GENERATED = {ROOT / "docs" / "reference" / "scenario.md"}


def doc_files() -> list[Path]:
    """README.md and every Markdown file under docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def code_blocks(text: str) -> list[tuple[int, str, str, bool]]:
    """``(line, language, code, skipped)`` for every fenced block of ``text``.

    Examples
    --------
    >>> code_blocks("x\\n```python\\n1 + 1\\n```\\n")
    [(2, 'python', '1 + 1\\n', False)]
    """
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, lang = i, m.group(1)
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        skipped = start > 0 and lines[start - 1].strip() == SKIP_MARK
        blocks.append(
            (start + 1, lang, "".join(line + "\n" for line in lines[start + 1 : j]), skipped)
        )
        i = j + 1
    return blocks


def python_examples() -> list:
    cases = []
    for path in doc_files():
        for line, lang, code, skipped in code_blocks(path.read_text(encoding="utf-8")):
            if lang != "python":
                continue
            marks = [pytest.mark.skip(reason=f"marked {SKIP_MARK}")] if skipped else []
            name = f"{path.relative_to(ROOT)}:{line}"
            cases.append(pytest.param(path, line, code, id=name, marks=marks))
    return cases


def test_docs_exist():
    """The README links into docs/, and it stays a front door (the package description)."""
    assert (ROOT / "docs" / "index.md").is_file()
    assert len((ROOT / "README.md").read_bytes()) <= 12_000
    assert len(python_examples()) >= 5


@pytest.mark.parametrize("path, line, code", python_examples())
def test_python_example_runs(path: Path, line: int, code: str, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__doc_example__"}
    with _logging_restored():  # an example may configure logging, as a user's program does
        exec(compile(code, f"{path}:{line}", "exec"), namespace)


@contextlib.contextmanager
def _logging_restored():
    """The root logger's handlers and the project's loggers' levels as they were before."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    names = [n for n in logging.root.manager.loggerDict if n.startswith("quadobs")]
    levels = {n: logging.getLogger(n).level for n in names}
    try:
        yield
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
        for n in logging.root.manager.loggerDict:
            if n.startswith("quadobs"):
                logging.getLogger(n).setLevel(levels.get(n, logging.NOTSET))


def relative_links(text: str) -> list[str]:
    """Targets of the Markdown links in ``text`` that are neither URLs nor in-page anchors.

    Examples
    --------
    >>> relative_links("[a](b.md#x) [c](https://d) [e](#f)")
    ['b.md#x']
    """
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    return [t for t in LINK.findall(text) if not re.match(r"^([a-z]+:|#)", t)]


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path: Path):
    missing = []
    for target in relative_links(path.read_text(encoding="utf-8")):
        file = target.split("#", 1)[0]
        target_path = (path.parent / file).resolve()
        if file and not target_path.exists() and target_path not in GENERATED:
            missing.append(target)
    assert not missing, f"{path.relative_to(ROOT)}: links to missing files: {missing}"


def test_no_source_text_names():
    """Papers are cited by key ([IFAC2021, eq. 15]), never by the file names of their texts."""
    pattern = re.compile(r"\d{3}_[0-9a-f]{16}\.txt")
    offenders = []
    for base in ("quadobs", "sims", "docs", "tests"):
        for file in sorted((ROOT / base).rglob("*")):
            if file.suffix in {".py", ".md", ".toml"} and pattern.search(
                file.read_text(encoding="utf-8")
            ):
                offenders.append(str(file.relative_to(ROOT)))
    if pattern.search((ROOT / "README.md").read_text(encoding="utf-8")):
        offenders.append("README.md")
    assert not offenders, offenders


def test_checks_detect_problems():
    """The extractor and the link check see what they must (so the tests above can fail)."""
    text = f"```python\nraise RuntimeError\n```\n{SKIP_MARK}\n```python\nslow()\n```\n```bash\nls\n```\n"
    blocks = code_blocks(text)
    assert [(b[1], b[3]) for b in blocks] == [("python", False), ("python", True), ("bash", False)]
    with pytest.raises(RuntimeError):
        exec(compile(blocks[0][2], "example", "exec"), {})
    assert relative_links("see [x](docs/nowhere.md) and [y](https://a.b)") == ["docs/nowhere.md"]
