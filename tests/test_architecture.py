"""The package's shape: imports point down only, no import cycles, and importing gpg changes no
global state (docs/design.md, Architecture)."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "gpg"

# Lower rank first. A module may import modules of a lower rank, or of its own group (the
# same subpackage); ranks shared by two groups keep those groups independent of each other
# (the GP numerics know nothing of quadrotors, the physics nothing of GPs).
RANKS = {
    "gpg._checks": 0,
    "gpg._io": 0,
    "gpg._interrupt": 0,
    "gpg._version": 0,
    "gpg._dtype": 0,
    "gpg._host": 0,
    "gpg._precision": 0,
    "gpg._identity": 0,
    "gpg._deprecated": 0,
    "gpg.runtime": 0.5,
    "gpg.results": 1,
    "gpg.parallel": 0,
    "gpg.names": 0,
    "gpg.conf": 0,
    "gpg.linalg": 1,
    "gpg.gp": 2,
    "gpg.quadrotor": 2,
    "gpg.data": 3,
    "gpg.config": 4,
    "gpg.kinds": 4.5,
    "gpg.models": 5,
    "gpg.design": 5.5,
    "gpg.surrogate": 6,
    "gpg.checkpoint": 7,
    "gpg.envs": 7,
    "gpg.mpc": 7,
    "gpg.adapters": 7,
    "gpg.export": 7,
    "gpg.flight": 7,
    "gpg": 8,
    "gpg.runs": 9,  # the deprecated forwarding to experiments.runs, nothing of its own
}


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Every gpg module ``name`` imports, at module level or inside a function."""
    is_pkg = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")[: len(name.split(".")) - node.level + is_pkg]
                base = ".".join(anchor + ([base] if base else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.add(sub if sub in known else base)
    return {m for m in found if m in known and m != name}


def _group(module: str) -> str | None:
    """The longest entry of RANKS that is ``module`` or contains it (the root only itself)."""
    hits = [g for g in RANKS if module == g or (g != "gpg" and module.startswith(g + "."))]
    return max(hits, key=len) if hits else None


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {name: _imports(name, path, set(mods)) for name, path in mods.items()}


def test_every_module_has_a_rank():
    assert [m for m in _modules() if _group(m) is None] == []


def test_imports_point_down():
    upward = []
    for a, deps in _graph().items():
        ga = _group(a)
        for b in deps:
            gb = _group(b)
            if gb == ga:
                continue
            if RANKS[gb] >= RANKS[ga]:
                upward.append(f"{a} -> {b}")
    assert upward == []


def test_no_import_cycles():
    graph = _graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        stack.append(node)
        for dep in sorted(graph[node]):
            if state.get(dep) == 1:
                cycles.append(" -> ".join(stack[stack.index(dep) :] + [dep]))
            elif dep not in state:
                visit(dep, stack)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    assert cycles == []


def test_the_walk_sees_function_level_imports(tmp_path):
    """The check would catch an upward import hidden inside a function."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from gpg.surrogate import Surrogate\n")
    assert _imports("gpg.quadrotor.m", src, {"gpg.surrogate"}) == {"gpg.surrogate"}


def test_import_changes_no_global_state():
    """In a fresh interpreter: x64, async dispatch, the signal handlers and the matplotlib
    backend untouched, and neither hydra nor matplotlib imported. The handlers are compared
    with what the interpreter started with: a shell's background job starts with SIGINT
    ignored, and that is its parent's choice, not gpg's."""
    code = (
        "import signal, sys, jax\n"
        "FLAGS = ('jax_enable_x64', 'jax_cpu_enable_async_dispatch')\n"
        "flags = lambda: tuple(jax.config.read(k) for k in FLAGS)\n"
        "handlers = lambda: tuple(signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM))\n"
        "before, sig_before = flags(), handlers()\n"
        "import gpg, gpg.data, gpg.quadrotor, gpg.checkpoint\n"
        "after = flags()\n"
        "assert before == after == (False, True), (before, after)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('hydra', 'matplotlib'))\n"
        "assert not bad, bad\n"
        "assert handlers() == sig_before, (sig_before, handlers())\n"
    )
    env = {k: v for k, v in __import__("os").environ.items() if not k.startswith("JAX_")}
    p = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert p.returncode == 0, p.stderr[-3000:]


MAX_FUNCTION_LINES = 60
LONG_REASON = "# Long by design:"


def test_no_long_function_without_a_reason():
    """No function in gpg/ longer than 60 lines (its docstring left out) unless the comment
    just above it says why (docs/design.md, Architecture)."""
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        lines = path.read_text().splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            n = node.end_lineno - node.lineno + 1
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                n -= first.end_lineno - first.lineno + 1
            top = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            above = "\n".join(lines[max(0, top - 5) : top - 1])
            if n > MAX_FUNCTION_LINES and LONG_REASON not in above:
                long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


def _signature_and_docstring_lines(tree: ast.AST) -> set[int]:
    """Lines of function signatures, docstrings, imports and field declarations: parameter
    lists and the fields of related records repeat by nature."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            top = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            out.update(range(top, node.body[0].lineno))
        if isinstance(node, ast.ImportFrom | ast.Import):
            out.update(range(node.lineno, node.end_lineno + 1))
        if isinstance(node, ast.AnnAssign) and node.value is None:  # a field declaration
            out.add(node.lineno)
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr):
            if isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
                out.update(range(body[0].lineno, body[0].end_lineno + 1))
    return out


def test_no_repeated_block_of_six_lines():
    """No block of six or more identical lines of code appears twice in gpg/ (one formula, one
    place): comments, imports, signatures, field declarations and docstrings are left out."""
    seen: dict[tuple[str, ...], str] = {}
    repeats = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        skip = _signature_and_docstring_lines(ast.parse(text))
        code = [
            (i, ln.strip())
            for i, ln in enumerate(text.splitlines(), 1)
            if ln.strip() and i not in skip and not ln.strip().startswith(("#", "import ", "from "))
        ]
        for k in range(len(code) - 5):
            block = tuple(c for _, c in code[k : k + 6])
            if all(len(c) < 12 for c in block):  # closing brackets and short keywords
                continue
            where = f"{path.relative_to(ROOT)}:{code[k][0]}"
            if block in seen:
                repeats.append(f"{seen[block]} and {where}")
            seen.setdefault(block, where)
    assert not repeats, repeats[:10]


def test_no_private_name_crosses_packages():
    """A name with a leading underscore is its package's own: no other package imports it
    (gpg's private top-level modules, ``gpg._checks`` and the like, serve the whole package)."""
    crossing = []
    mods = _modules()
    for name, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.ImportFrom) and (node.module or "").startswith("gpg.")):
                continue
            for a in node.names:
                private = a.name.startswith("_") and not a.name.startswith("__")
                if private and _group(node.module) != _group(name):
                    crossing.append(f"{path.relative_to(ROOT)}:{node.lineno} {a.name}")
    assert not crossing, crossing


def _private_gpg_imports(path: Path) -> list[str]:
    """The private gpg modules and names ``path`` imports (``gpg._io``, ``_grown_rows``)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
            names: list[str] = []
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            mods = [node.module or ""]
            names = [a.name for a in node.names]
        else:
            continue
        for m in mods:
            if m.split(".")[0] != "gpg":
                continue
            parts = m.split(".") + names
            if any(p.startswith("_") and not p.startswith("__") for p in parts):
                out.append(f"{path.name}:{node.lineno} {m} {names}")
    return out


def test_experiments_use_the_public_api_only():
    """The experiments live outside the installed package and use gpg as a user does: no
    private module or name of gpg (``gpg.runtime`` has what a long run needs)."""
    found = []
    for path in sorted((ROOT / "experiments").rglob("*.py")):
        found += _private_gpg_imports(path)
    assert found == []


def test_the_private_import_check_sees_modules_and_names(tmp_path):
    src = tmp_path / "m.py"
    src.write_text(
        "from gpg._io import atomic_write\nfrom gpg.gp.update import _grown\nimport gpg._dtype\n"
        "from gpg.runtime import float64\n"
    )
    assert [f.split()[0] for f in _private_gpg_imports(src)] == ["m.py:1", "m.py:2", "m.py:3"]


def test_the_package_installs_no_experiment_code():
    """``pip install .`` installs ``gpg`` only: the experiments, their configs and the
    benchmarks stay in the repository (gpg.runs is a forwarding shim with no code of its
    own)."""
    import tomllib

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert cfg["tool"]["setuptools"]["packages"]["find"]["include"] == ["gpg*"]
    assert sorted(p.name for p in (PACKAGE / "runs").iterdir() if p.suffix == ".py") == [
        "__init__.py"
    ]
