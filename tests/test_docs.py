"""The documentation cannot rot: every ```python block of docs/*.md and README.md runs.

The blocks of one page run in order in one namespace (a page is a tutorial: later blocks use
what earlier ones defined), in a temporary working directory. A block that genuinely cannot
run is opted out by the HTML comment ``<!-- docs: skip -->`` on the line before its fence
(invisible on the site); shell commands go in ```bash blocks, which are never run.
The site itself must build with ``mkdocs build --strict`` (skipped without mkdocs).
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import plugin_marks

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [*sorted(DOCS.glob("*.md")), ROOT / "README.md"]
SKIP = "<!-- docs: skip -->"
FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^\n`]*)$")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line number, source)`` of each ```python block not opted out with SKIP.

    Fences may be indented (inside admonitions or lists); the indentation is removed.
    """
    lines = text.splitlines()
    blocks: list[tuple[int, str]] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m is None:
            i += 1
            continue
        indent, fence = m.group("indent"), m.group("fence")
        lang = m.group("info").strip().split(" ")[0].strip("{}.").lower()
        start = i
        body: list[str] = []
        i += 1
        close = re.compile(re.escape(fence[0]) + f"{{{len(fence)},}}")
        while i < len(lines) and not close.fullmatch(lines[i].strip()):
            body.append(lines[i][len(indent) :] if lines[i].startswith(indent) else lines[i])
            i += 1
        i += 1
        previous = next((ln.strip() for ln in reversed(lines[:start]) if ln.strip()), "")
        if lang in ("python", "py") and previous != SKIP:
            blocks.append((start + 1, "\n".join(body) + "\n"))
    return blocks


def run_blocks(blocks: list[tuple[int, str]], page: str) -> dict[str, object]:
    """Run the blocks in order in one fresh namespace, as the script a reader would paste
    them into (``__name__ == "__main__"``: a guarded block runs); an exception fails with
    its location."""
    namespace: dict[str, object] = {"__name__": "__main__", "__file__": page}
    for line, source in blocks:
        label = f"{page}:{line}"
        code = compile(source, label, "exec")
        try:
            exec(code, namespace)
        except Exception as exc:
            raise AssertionError(f"the example at {label} raised {type(exc).__name__}") from exc
    return namespace


def test_fence_parser() -> None:
    text = "\n".join(
        [
            "```python",
            "a = 1",
            "```",
            "```bash",
            "pip install x",
            "```",
            SKIP,
            "```python",
            "raise SystemExit",
            "```",
            "!!! note",
            "    ```python",
            "    b = a + 1",
            "    ```",
        ]
    )
    assert python_blocks(text) == [(1, "a = 1\n"), (12, "b = a + 1\n")]


def test_a_failing_example_fails() -> None:
    blocks = python_blocks("```python\nx = 1\n```\n\n```python\ny = x / 0\n```\n")
    with pytest.raises(AssertionError, match=r"page.md:5 raised ZeroDivisionError"):
        run_blocks(blocks, "page.md")
    assert run_blocks(blocks[:1], "page.md")["x"] == 1


def test_a_main_guarded_example_runs() -> None:
    """docs/sweeps.md guards its ``lf.sweep`` call as a script must; the guarded block is
    run (and can fail) like any other."""
    blocks = python_blocks('```python\nif __name__ == "__main__":\n    ran = True\n```\n')
    assert run_blocks(blocks, "page.md")["ran"] is True
    sweeps = (ROOT / "docs" / "sweeps.md").read_text(encoding="utf-8")
    block = next(code for _, code in python_blocks(sweeps) if "lf.sweep(" in code)
    assert 'if __name__ == "__main__":' in block
    assert block.index('if __name__ == "__main__":') < block.index("lf.sweep(")


def test_turbulence_page_plots_the_file_its_run_writes() -> None:
    """docs/turbulence.md's commands, from the repository root: ``lieflow plot`` opens the
    file ``lieflow run`` wrote (``[run] output`` is relative to the configuration's folder;
    ``--out`` to the working directory)."""
    import shlex

    text = (ROOT / "docs" / "turbulence.md").read_text(encoding="utf-8")
    run = shlex.split(re.search(r"^lieflow run .*$", text, re.M).group(0))  # type: ignore[union-attr]
    plot = shlex.split(re.search(r"^lieflow plot .*$", text, re.M).group(0))  # type: ignore[union-attr]
    config = ROOT / run[2]
    if "--out" in run:
        written = ROOT / run[run.index("--out") + 1]
    else:
        output = re.search(r'^output = "(.*)"$', config.read_text(encoding="utf-8"), re.M)
        written = config.parent / output.group(1)  # type: ignore[union-attr]
    assert (ROOT / plot[2]).resolve() == written.resolve()


def test_every_page_is_checked() -> None:
    """Each page with Python examples is exercised; the tutorial pages have some."""
    with_code = {p.name for p in PAGES if python_blocks(p.read_text(encoding="utf-8"))}
    for page in ("getting-started.md", "choosing.md", "systems.md", "plugins.md", "theory.md"):
        assert page in with_code, f"docs/{page} has no runnable example"


def _page(page: Path) -> object:
    """The page as a parameter, skipped where a plugin that its examples use is missing."""
    code = "".join(source for _, source in python_blocks(page.read_text(encoding="utf-8")))
    return pytest.param(page, marks=plugin_marks(code), id=page.relative_to(ROOT).as_posix())


@pytest.mark.parametrize("page", [_page(page) for page in PAGES])
def test_examples_run(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = python_blocks(page.read_text(encoding="utf-8"))
    if not blocks:
        pytest.skip("no python examples")
    pytest.importorskip("matplotlib").use("Agg")
    monkeypatch.chdir(tmp_path)
    run_blocks(blocks, page.relative_to(ROOT).as_posix())


# .ci/run builds the site with warnings as errors on every submission; here -m slow
@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None
    or importlib.util.find_spec("mkdocstrings_handlers") is None,
    reason="mkdocs / mkdocstrings not installed (pip install -e '.[docs]')",
)
def test_site_builds_strict(tmp_path: Path) -> None:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "WARNING" not in proc.stderr, proc.stderr
    assert (tmp_path / "index.html").is_file()


def test_griffe_extension_rewrites_rst() -> None:
    """docs/griffe_lieflow.py turns the docstrings' reStructuredText into Markdown."""
    pytest.importorskip("griffe")
    sys.path.insert(0, str(DOCS))
    try:
        from griffe_lieflow import rst_to_markdown, split_groups
    finally:
        sys.path.remove(str(DOCS))
    text = "See :class:`~lieflow.errors.InputError` and :math:`h^2`:\n\n.. math:: a = b\n"
    assert rst_to_markdown(text) == "See `InputError` and \\(h^2\\):\n\n\n\\[\na = b\n\\]\n"
    doc = "Parameters\n----------\nrtol, atol : float, float\n    Tolerances.\n"
    assert split_groups(doc) == (
        "Parameters\n----------\nrtol : float\n    Tolerances.\natol : float\n    Tolerances."
    )
