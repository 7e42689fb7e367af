"""The README's Python blocks run as written (```python blocks; ```py blocks illustrate calls
on the reader's own files, and notebooks/04_your_own_vehicle.ipynb runs those steps). A block
whose first line is ``# continues the block above`` runs in the namespace of the one before."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
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


CHAINS = chains(BLOCKS)


@pytest.mark.parametrize("index", range(len(CHAINS)))
def test_readme_block_runs(index, capsys):
    namespace = {"__name__": "__readme__"}
    for i, block in enumerate(CHAINS[index]):
        exec(compile(block, f"README.md chain {index}, block {i}", "exec"), namespace)


FRESH = """
import sys, warnings
import jax
if sys.argv[1] == "float64":
    jax.config.update("jax_enable_x64", True)
warnings.filterwarnings("error", message=".*truncated to dtype float32")  # none on the way
code = sys.stdin.read()
exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
"""


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("index", range(len(CHAINS)))
def test_readme_chain_in_a_fresh_interpreter(index, dtype, tmp_path):
    """As a user runs it: a new interpreter, outside the repository, in a float32 program (JAX's
    default) and in a float64 one."""
    import subprocess
    import sys

    code = "\n".join(CHAINS[index])
    res = subprocess.run(
        [sys.executable, "-c", FRESH, dtype],
        input=code,
        text=True,
        capture_output=True,
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr[-3000:]
