"""The README's and the docs pages' Python blocks run as written (```python blocks; ```py
blocks illustrate calls on the reader's own files, and notebooks/04_your_own_vehicle.ipynb runs
those steps). A block whose first line is ``# continues the block above`` runs in the namespace
of the one before. Every relative link of those pages points at a file and heading that exist."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
CONTINUED = "# continues the block above"


def chains(blocks: list[str]) -> list[list[str]]:
    """Consecutive blocks that continue each other, grouped."""
    out: list[list[str]] = []
    for b in blocks:
        if b.startswith(CONTINUED) and out:
            out[-1].append(b)
        else:
            out.append([b])
    return out


def page_chains(page: Path) -> list[list[str]]:
    return chains(re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S))


CHAINS = page_chains(README)
DOC_CHAINS = [(p.name, i, c) for p in PAGES[1:] for i, c in enumerate(page_chains(p))]


def in_process(chains, ids):
    """Chains that fit a quadrotor surrogate (generate data, then a likelihood fit: 10-25 s
    each) run in the slow set only, where every chain also runs in fresh float32 and float64
    interpreters; each step they take has a fast test of its own. The rest run here."""
    heavy = [any("Surrogate.fit(" in b for b in c[-1]) for c in chains]
    return [
        pytest.param(*c, id=i, marks=[pytest.mark.slow] if h else [])
        for c, i, h in zip(chains, ids, heavy, strict=True)
    ]


@pytest.mark.parametrize(
    "index, chain",
    in_process([(i, c) for i, c in enumerate(CHAINS)], [str(i) for i in range(len(CHAINS))]),
)
def test_readme_block_runs(index, chain, capsys):
    namespace = {"__name__": "__readme__"}
    for i, block in enumerate(chain):
        exec(compile(block, f"README.md chain {index}, block {i}", "exec"), namespace)


@pytest.mark.parametrize(
    "page, index, chain", in_process(DOC_CHAINS, [f"{p}-{i}" for p, i, _ in DOC_CHAINS])
)
def test_docs_block_runs(page, index, chain, capsys):
    namespace = {"__name__": "__readme__"}
    for i, block in enumerate(chain):
        exec(compile(block, f"docs/{page} chain {index}, block {i}", "exec"), namespace)


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown page (headings outside code blocks)."""
    out, fence = set(), False
    for line in page.read_text().splitlines():
        fence ^= line.startswith("```")
        if not fence and re.match(r"#{1,6} ", line):
            out.add(re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower()).replace(" ", "-"))
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists() or (anchor and dest.suffix == ".md" and anchor not in _anchors(dest)):
            broken.append(target)
    assert not broken, f"{page.name}: broken links {broken}"


FRESH = """
import sys, warnings
import jax
if sys.argv[1] == "float64":
    jax.config.update("jax_enable_x64", True)
warnings.filterwarnings("error", message=".*truncated to dtype float32")  # none on the way
code = sys.stdin.read()
exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
"""


ALL_CHAINS = [("README.md", i, c) for i, c in enumerate(CHAINS)] + DOC_CHAINS


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize(
    "page, index, chain", ALL_CHAINS, ids=[f"{p}-{i}" for p, i, _ in ALL_CHAINS]
)
def test_readme_chain_in_a_fresh_interpreter(page, index, chain, dtype, tmp_path):
    """As a user runs it: a new interpreter, outside the repository, in a float32 program (JAX's
    default) and in a float64 one."""
    import subprocess
    import sys

    code = "\n".join(chain)
    res = subprocess.run(
        [sys.executable, "-c", FRESH, dtype],
        input=code,
        text=True,
        capture_output=True,
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr[-3000:]
