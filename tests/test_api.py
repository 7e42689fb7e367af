"""The public API as its readers find it (docs/design.md, "Layout"): every public module says
what it exports (``__all__``), every exported function and method documents its arguments,
its result and what it raises in Google-style sections (rendered as tables on the site), and
no machine-measured figure sits in the source, where it would go stale (the figures live in
docs/measurements.md, beside the command that measures them)."""

from __future__ import annotations

import ast
import io
import logging
import re
import textwrap
import tokenize
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "gpg"


def _public_files() -> dict[str, Path]:
    """Dotted name -> file of every public module (no part of its path starts with ``_``)."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if not any(p.startswith("_") for p in parts):
            out[".".join(parts)] = path
    return out


def _declared_all(path: Path) -> list[str] | None:
    for node in ast.parse(path.read_text()).body:
        targets = node.targets if isinstance(node, ast.Assign) else []
        if isinstance(node, ast.AnnAssign) and node.value is not None:
            targets = [node.target]
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            return list(ast.literal_eval(node.value))
    return None


def test_every_public_module_declares_all():
    """A module is private (``_name``) or lists its public names in ``__all__``."""
    missing = [name for name, path in _public_files().items() if _declared_all(path) is None]
    assert missing == []


@cache
def _griffe_package():
    import griffe

    return griffe.load("gpg", search_paths=[str(ROOT)], docstring_parser="google")


def test_every_exported_name_exists():
    pkg = _griffe_package()
    absent = []
    for name, path in _public_files().items():
        mod = pkg if name == "gpg" else pkg[name.removeprefix("gpg.")]
        absent += [f"{name}.{n}" for n in _declared_all(path) or () if n not in mod.members]
    assert absent == []


def _raises(source: str) -> bool:
    """Whether a function raises an exception itself (a nested function's raise is its own,
    a bare ``raise`` re-raises the caller's)."""
    tree = ast.parse(textwrap.dedent(source))
    fn = tree.body[0]
    stack = list(fn.body)
    while stack:
        node = stack.pop()
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda | ast.ClassDef):
            continue
        if isinstance(node, ast.Raise) and node.exc is not None:
            return True
        stack.extend(ast.iter_child_nodes(node))
    return False


def _needs(fn) -> set[str]:
    """The sections a function's docstring must have."""
    need = set()
    if [p for p in fn.parameters if p.name not in ("self", "cls")]:
        need.add("parameters")
    returns = str(fn.returns) if fn.returns is not None else None
    if returns not in ("None", "NoReturn"):
        need.add("returns")
    if _raises(fn.source):
        need.add("raises")
    return need


def _documented(obj) -> list:
    """The exported functions and the public methods of the exported classes of ``obj``."""
    out = []
    for name in obj.exports or ():
        member = obj.members.get(name if isinstance(name, str) else name.name)
        if member is None or member.is_alias:
            continue
        if member.is_function:
            out.append(member)
        elif member.is_class:
            out += [
                m
                for n, m in member.members.items()
                if not n.startswith("_")
                and not m.is_alias
                and m.is_function
                and "property" not in m.labels
            ]
    return out


def missing_sections(prefix: str = "gpg") -> list[str]:
    """``path: sections`` for every exported function or method under ``prefix`` whose
    docstring lacks a section it needs (``python -c "from tests.test_api import
    missing_sections as m; print(*m('gpg.gp'), sep='\\n')"`` lists a subpackage's)."""
    pkg = _griffe_package()
    out = []
    for name in _public_files():
        if not (name == prefix or name.startswith(prefix + ".")):
            continue
        mod = pkg if name == "gpg" else pkg[name.removeprefix("gpg.")]
        for fn in _documented(mod):
            have = {s.kind.value for s in fn.docstring.parsed} if fn.docstring else set()
            have |= {"returns"} if "yields" in have else set()
            lack = _needs(fn) - have
            if lack:
                out.append(f"{fn.path}: {', '.join(sorted(lack))}")
    return out


def test_exported_functions_document_args_returns_raises():
    assert missing_sections() == []


def _parse_warnings(functions, caplog) -> list[str]:
    """What griffe warns while parsing the docstrings of ``functions`` afresh (``parsed`` is
    cached: a docstring parsed once before would warn no more)."""
    with caplog.at_level(logging.WARNING, logger="griffe"):
        caplog.clear()
        for fn in functions:
            if fn.docstring:
                fn.docstring.parse("google")
    return [r.getMessage() for r in caplog.records]


def test_docstrings_parse_without_warnings(caplog):
    """What mkdocstrings would warn about (``make docs`` is strict): a documented parameter
    that does not exist or has no type, a section that does not parse."""
    pkg = _griffe_package()
    functions = []
    for name in _public_files():
        functions += _documented(pkg if name == "gpg" else pkg[name.removeprefix("gpg.")])
    assert _parse_warnings(functions, caplog) == []


def test_the_parse_check_sees_a_parameter_that_is_not_there(caplog):
    import griffe

    code = (
        'def f(a: int) -> int:\n    """Sum.\n\n'
        '    Args:\n        b: x.\n\n    Returns:\n        y.\n    """\n'
    )
    mod = griffe.visit("m", filepath=None, code=code, docstring_parser="google")
    found = _parse_warnings([mod["f"]], caplog)
    assert any("'b' does not appear in the function signature" in w for w in found), found


def test_the_section_check_sees_a_raise_and_ignores_a_nested_one():
    assert _raises("def f(x):\n    if x:\n        raise ValueError('x')\n")
    assert not _raises("def f(x):\n    def g():\n        raise ValueError\n    return g\n")
    assert not _raises("def f(x):\n    try:\n        pass\n    except E:\n        raise\n")


# Figures that come from a machine (times, speed-ups, memory measured, errors measured) go
# stale in the code: docs/measurements.md holds them, with their commands. What the pattern
# still finds and is not a measurement is listed here, each with the reason.
_FIGURE = re.compile(
    r"(?<![\w.^])\d+(?:\.\d+)?\s*(?:x|×)(?![\w(])"  # a ratio: 3x faster
    r"|(?<![\w.^])\d+(?:\.\d+)?\s*(?:s|ms|us|µs|ns|min|MiB|GiB|KiB|MB|GB|kB|%)(?![\w/²])"
)
ALLOWED = {
    # The method's definition (the paper's perturbation), not a measurement.
    ("gpg/data/sampling.py", "raised by 10 %"),
    ("gpg/data/sampling.py", "(a 10 % step of nothing)"),
    # A count of cases: each mirror doubles the dataset.
    ("gpg/data/symmetry.py", "2x the"),
    ("gpg/data/symmetry.py", "4x)"),
    # Arithmetic on the model (a first-order expansion), not a measurement.
    ("gpg/quadrotor/bemt.py", "(3.4 % for κ² = 0.15)"),
    # The scenario's ranges: parameters of the randomisation.
    ("gpg/quadrotor/rollout.py", "±30 %"),
    ("gpg/quadrotor/rollout.py", "2–8 s period"),
}


def _comments_and_docstrings(path: Path):
    """(line number, text) of every comment and triple-quoted string of ``path``."""
    for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        text = tok.string
        if tok.type == tokenize.COMMENT or (
            tok.type == tokenize.STRING and text.lstrip("rbuRBU").startswith(('"""', "'''"))
        ):
            for i, line in enumerate(text.splitlines()):
                yield tok.start[0] + i, line


def measured_figures() -> list[str]:
    """``path:line: text`` of every figure in gpg's comments and docstrings not allowed."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = str(path.relative_to(ROOT))
        allowed = [frag for f, frag in ALLOWED if f == rel]
        for line_no, line in _comments_and_docstrings(path):
            rest = line
            for frag in allowed:
                rest = rest.replace(frag, "")
            if _FIGURE.search(rest):
                out.append(f"{rel}:{line_no}: {line.strip()}")
    return out


def test_no_measured_figure_in_the_source():
    assert measured_figures() == []


def test_the_figure_pattern_finds_times_ratios_and_sizes():
    for text in ("takes 2.6 s", "15.9 -> 11.3 us", "3x faster", "12.8 GB", "56 % of"):
        assert _FIGURE.search(text), text
    for text in ("x1 x2", "10^3", "e.g. 2", "float32", "(N, 3)", "1e-5", "h in ft"):
        assert not _FIGURE.search(text), text


def test_the_section_check_asks_for_what_a_function_has():
    import griffe

    code = (
        "def f(a: int) -> int:\n    '''No sections.'''\n    if a < 0:\n        raise ValueError\n"
        "    return a\n\ndef g() -> None:\n    '''Nothing to document.'''\n"
    )
    with griffe.temporary_visited_module(code) as mod:
        assert _needs(mod["f"]) == {"parameters", "returns", "raises"}
        assert _needs(mod["g"]) == set()
