"""A griffe extension (``mkdocs.yml``, mkdocstrings' ``extensions``): gpg's docstrings name
other objects with Sphinx roles (``:class:`Surrogate```, ``:func:`gpg.gp.gram.observed_rows```),
which Markdown would print as they are. Each role becomes a link to the object's entry in the
reference when the name resolves, from the docstring's own scope as Python would resolve it,
to an object the reference documents; otherwise a code span."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import griffe

sys.path.insert(0, str(Path(__file__).parent))
import hooks  # noqa: E402 (the reference's entries: hooks.identifiers)

ROLE = re.compile(r":(?:class|func|meth|data|attr|mod|obj|exc):`~?([^`]+)`")


def resolve(obj: griffe.Object, name: str) -> str | None:
    """The reference entry ``name`` means in ``obj``'s docstring, or None."""
    entries = hooks.identifiers()
    if name in entries:
        return entries[name]
    scope = obj
    while scope is not None:
        head, _, rest = name.partition(".")
        member = scope.members.get(head) if hasattr(scope, "members") else None
        if member is not None:
            try:
                path = member.final_target.path if member.is_alias else member.path
            except griffe.AliasResolutionError:  # a name from outside gpg (jax, numpy)
                return None
            full = f"{path}.{rest}" if rest else path
            return entries.get(full)
        scope = scope.parent
    return None


class Roles(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        def visit(obj) -> None:
            if obj.is_alias:
                return
            if obj.docstring is not None:
                obj.docstring.value = ROLE.sub(lambda m: link(obj, m.group(1)), obj.docstring.value)
            for member in obj.members.values():
                if not member.is_alias:
                    visit(member)

        def link(obj, name: str) -> str:
            target = resolve(obj, name.strip("()"))
            return f"[`{name}`][{target}]" if target else f"`{name}`"

        visit(pkg)
