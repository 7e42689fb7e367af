"""MkDocs hooks of gpg's site (``mkdocs.yml``; ``make docs``).

The Markdown pages stay what GitHub shows (``docs/*.md``, the README at the root); these hooks
make the same files a site:

- the README becomes the landing page and ``examples/c_flight`` and ``examples/c_adapt``
  guides, their links rewritten from the repository's layout to the site's;
- the notebooks are executed (top to bottom, from the repository root, as a user runs them)
  and added with their outputs; an executed copy is kept under ``build/docs/`` keyed by the
  notebook's bytes and gpg's version, so a rebuild does not run them again;
- the API reference is generated: one page per part of the package, an entry for every
  public module and name (:func:`reference_pages`);
- a name in a code span (``gpg.data.from_csv``, ``Surrogate.predict``) links to its entry in
  the reference (:func:`link_names`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import time
from functools import cache
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
CACHE = ROOT / "build" / "docs"
CARRIED = ("examples/c_flight", "examples/c_adapt", "notebooks")  # folders the site carries
log = logging.getLogger("mkdocs.plugins.gpg")

# Top-level modules with a reference page of their own; the other top-level modules share
# the page "gpg" with the package itself. Packages always have their own.
OWN_PAGE = ("surrogate", "mpc")
# Modules kept for one release to forward an old name (no code, no reference entry).
DEPRECATED = ("gpg.runs",)


# ---------------------------------------------------------------------------------------------
# The API reference


@cache
def package():
    """gpg as griffe reads it (statically, as mkdocstrings renders it)."""
    import griffe

    return griffe.load("gpg", search_paths=[str(ROOT)], docstring_parser="google")


def lookup(path: str):
    """The griffe object at a dotted path (``gpg.data.dataset.Dataset``)."""
    return package() if path == "gpg" else package()[path.removeprefix("gpg.")]


def public_modules() -> list[str]:
    """Every public module of gpg, dotted, in a stable order (no part starts with ``_``)."""
    out: list[str] = []

    def walk(mod):
        out.append(mod.path)
        for name, sub in sorted(mod.modules.items()):
            if not name.startswith("_") and not sub.is_alias and sub.path not in DEPRECATED:
                walk(sub)

    walk(package())
    return out


def own_members(mod) -> list[str]:
    """The names of a module's ``__all__`` that it defines itself (not imported), in the order
    of its source, as mkdocstrings renders them."""
    exports = {e if isinstance(e, str) else e.name for e in mod.exports or ()}
    return [
        n
        for n, m in mod.members.items()
        if n in exports and not m.is_alias and not m.is_module and not n.startswith("_")
    ]


def reexports(mod) -> dict[str, str]:
    """A package's ``__all__`` names defined elsewhere: name -> the entry's dotted path."""
    out = {}
    for name in mod.exports or ():
        m = mod.members.get(name if isinstance(name, str) else name.name)
        if m is not None and m.is_alias:
            target = m.final_target.path
            if not any(part.startswith("_") for part in target.split(".")):
                out[m.name] = target
    return out


def page_of(module: str) -> str:
    """The reference page (``reference/<page>.md``) that documents ``module``."""
    parts = module.split(".")
    if len(parts) == 1:
        return "gpg"
    top = parts[1]
    return top if lookup(f"gpg.{top}").is_subpackage or top in OWN_PAGE else "gpg"


def reference_pages() -> dict[str, str]:
    """``reference/<page>.md`` -> its Markdown: each module's heading, docstring and members,
    and for a package the names it re-exports, linked to where they are documented."""
    pages: dict[str, list[str]] = {}
    for path in public_modules():
        mod = lookup(path)
        page = page_of(path)
        lines = pages.setdefault(page, [f"# {'gpg' if page == 'gpg' else 'gpg.' + page}", ""])
        own = own_members(mod)
        members = "false" if not own else "[" + ", ".join(own) + "]"
        lines += [f"::: {path}", "    options:", f"      members: {members}", ""]
        again = reexports(mod)
        if again:
            lines += [f"`{path}` also exports:", "", "| name | documented as |", "|---|---|"]
            lines += [f"| `{n}` | [`{t}`][{t}] |" for n, t in sorted(again.items())]
            lines.append("")
    return {f"reference/{p}.md": "\n".join(lines) for p, lines in pages.items()}


API_HEAD = """# Public API

Part of gpg's documentation ([contents](README.md); the project's [README](../README.md)).

Generated from the packages' `__all__` (`make api` writes this page; tests/test_docs.py checks
that it is current): every name gpg exports, with the first sentence of its docstring; on the
site each name links to its reference entry, with its arguments, returns and errors. A
package's `__init__` is the one place to import from: `from gpg.flight import correct`, and a
module it exports through it (`from gpg.gp import partition`, then `partition.build(...)`).
"""

API_TAIL = """
Bad input (mismatched shapes, NaN/inf, gradient dims out of range, non-positive
hyperparameters, unknown model names or config keys, sizes beyond the data) raises `ValueError`
naming the input; a NaN query to a GP model under `jit` raises through `eqx.error_if`, and the
`Surrogate` flags it with `in_domain = False`; a likelihood fit that does not converge warns (or
raises, on request).
"""


def summary(obj) -> str:
    """The first sentence of ``obj``'s docstring, on one line, its Sphinx roles as code."""
    if obj.is_alias:
        obj = obj.final_target
    text = obj.docstring.value if obj.docstring else ""
    text = " ".join(text.split("\n\n")[0].split())
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    m = re.search(r"(?<!\bEq)(?<!\bEqs)(?<!e\.g)(?<!i\.e)(?<!\bcf)(?<!\bvs)\.(\s|$)", text)
    first = (text[: m.start()] if m else text).strip()
    if not first and obj.is_attribute and obj.value is not None:
        value = str(obj.value)
        first = f"`{value if len(value) <= 60 else value[:57] + '...'}`"
    return first.replace("|", "\\|") or "(no docstring)"


def _exports(mod) -> list[str]:
    return [e if isinstance(e, str) else e.name for e in mod.exports or ()]


def api_overview() -> str:
    """``docs/api.md``: a table per package of ``gpg.__all__``, its exports and those of the
    modules it exports, one line each."""
    root = package()
    lines = [API_HEAD]
    sections = [("gpg", root)]
    sections += [
        (f"gpg.{n}", root.members[n])
        for n in sorted(_exports(root))
        if root.members[n].is_module and not root.members[n].is_alias
    ]
    for title, mod in sections:
        mod = mod.final_target if mod.is_alias else mod
        listed: set[str] = set()
        lines += [f"## `{title}`", "", summary(mod) + ".", "", "| name | what |", "|---|---|"]
        for n in _exports(mod):
            member = mod.members[n]
            target = member.final_target if member.is_alias else member
            if n.startswith("__") or (target.is_module and title == "gpg" and not member.is_alias):
                continue
            lines.append(f"| `{title}.{n}` | {summary(member)} |")
            listed.add(target.path)
            if target.is_module and not target.is_package and not member.is_alias:
                for m in _exports(target):
                    sub = target.members[m]
                    if (sub.final_target if sub.is_alias else sub).path not in listed:
                        lines.append(f"| `{title}.{n}.{m}` | {summary(sub)} |")
        lines.append("")
    return "\n".join(lines) + API_TAIL


@cache
def identifiers() -> dict[str, str]:
    """Every name a guide may write -> the dotted path of its reference entry: the canonical
    paths of public modules and of their members (and the members of their classes), the
    re-exported paths (``gpg.data.generate``), and ``gpg.__all__``'s names without the
    prefix (``Surrogate.predict``)."""
    out: dict[str, str] = {}

    def add(name: str, obj, target: str) -> None:
        out.setdefault(name, target)
        if obj.is_class:
            for n, m in obj.members.items():
                if not n.startswith("_") and not m.is_alias:
                    out.setdefault(f"{name}.{n}", f"{target}.{n}")

    for path in public_modules():
        mod = lookup(path)
        out[path] = path
        for n in own_members(mod):
            add(f"{path}.{n}", mod.members[n], f"{path}.{n}")
        for n, target in reexports(mod).items():
            add(f"{path}.{n}", lookup(target), target)
    for n, target in reexports(package()).items():
        if f"gpg.{n}" in out and n[0].isupper():
            add(n, lookup(target), target)
    return out


_SPAN = re.compile(r"(?<![\[`])`([A-Za-z_][\w.]*)(\([^`]*\))?`(?![\]`(])")


def link_names(markdown: str) -> str:
    """Code spans that name a documented object link to its entry (outside code blocks,
    headings and existing links; each name once a page, at its first mention)."""
    names, seen, out, fence = identifiers(), set(), [], False

    def link(m: re.Match) -> str:
        name = m.group(1).rstrip(".")
        while name and name not in names:
            name = name.rpartition(".")[0]
        if not name or "." not in m.group(1) and m.group(1) not in names:
            return m.group(0)
        target = names[name]
        if target in seen:
            return m.group(0)
        seen.add(target)
        return f"[{m.group(0)}][{target}]"

    for line in markdown.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fence = not fence
        out.append(line if fence or line.startswith("#") else _SPAN.sub(link, line))
    return "\n".join(out) + ("\n" if markdown.endswith("\n") else "")


# ---------------------------------------------------------------------------------------------
# Notebooks

# The notebooks' environment on the site: no progress bars (tqdm's notebook widget needs
# ipywidgets, and a bar is noise on a page). Part of the cache key.
RUN_ENV = {"TQDM_DISABLE": "1"}
RUN = repr(sorted(RUN_ENV.items()))


def executed(notebook: Path) -> Path:
    """``notebook`` executed top to bottom from the repository root, cached by its bytes and
    gpg's version; a cell that raises fails the build."""
    import nbformat
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError

    from gpg import __version__

    key = hashlib.sha256(notebook.read_bytes() + RUN.encode() + __version__.encode())
    key = key.hexdigest()[:16]
    out = CACHE / "notebooks" / key / "notebooks" / notebook.name
    if out.is_file():
        return out
    log.info(f"executing {notebook.relative_to(ROOT)} (cached under {out.parent})")
    nb = nbformat.read(notebook, as_version=4)
    start = time.perf_counter()
    os.environ.update(RUN_ENV)  # the kernel inherits it
    try:
        NotebookClient(
            nb, timeout=1200, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
        ).execute()
    except CellExecutionError as e:
        raise PluginError(f"{notebook.name} failed:\n{str(e)[-3000:]}") from e
    log.info(f"executed {notebook.name} in {time.perf_counter() - start:.0f} s")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    nbformat.write(nb, tmp)
    os.replace(tmp, out)
    return out


# ---------------------------------------------------------------------------------------------
# Links from the repository's layout to the site's


def site_links(markdown: str, src: str) -> str:
    """Rewrite links written for GitHub: in the README (the landing page) ``docs/x`` is ``x``;
    in the pages ``../README.md`` is the landing page, as is ``README.md`` (GitHub's contents of
    docs/), and ``../examples/...`` the copy the site carries; a link to a folder of results is
    a link to its listing (:func:`listings`)."""
    top = src.count("/") == 0

    def fix(m: re.Match) -> str:
        target = m.group(2)
        if re.match(r"[a-z]+:", target) or target.startswith("#") or not top:
            return m.group(0)
        path, hash_, anchor = target.partition("#")
        if src == "index.md":
            path = path.removeprefix("docs/")
        elif path in ("../README.md", "README.md"):
            path = "index.md"
        elif path.startswith("../"):
            path = path[3:]
        if path and (ROOT / "docs" / path).is_dir():
            path = path.rstrip("/") + "/index.md"
        return f"{m.group(1)}({path}{hash_}{anchor})"

    return re.sub(r"(\])\(([^)\s]+)\)", fix, markdown)


def listings() -> dict[str, str]:
    """``results/<run>/index.md`` for each folder of raw results under docs/: what GitHub shows
    as a folder's listing, its files linked (the pages link to the folders)."""
    out = {}
    for folder in sorted(p for p in (ROOT / "docs" / "results").rglob("*") if p.is_dir()):
        rel = folder.relative_to(ROOT / "docs").as_posix()
        entries = sorted(folder.iterdir())
        lines = [f"# {rel}", "", "Raw results of the runs the pages quote.", ""]
        lines += [
            f"- [{p.name}{'/' if p.is_dir() else ''}]({p.name}{'/index.md' if p.is_dir() else ''})"
            for p in entries
        ]
        out[f"{rel}/index.md"] = "\n".join(lines) + "\n"
    return out


# ---------------------------------------------------------------------------------------------
# MkDocs events


@event_priority(100)  # before mkdocs-jupyter's on_files, which turns .ipynb files into pages
def on_files(files: Files, config) -> Files:
    def generated(uri: str, content: str) -> None:
        files.append(File.generated(config, uri, content=content))

    generated("index.md", (ROOT / "README.md").read_text(encoding="utf-8"))
    for folder in CARRIED:
        for path in sorted((ROOT / folder).iterdir()):
            if path.is_file() and path.suffix != ".ipynb":
                uri = f"{folder}/{path.name}"
                files.append(File(uri, str(ROOT), config["site_dir"], config["use_directory_urls"]))
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        done = executed(notebook)  # <cache>/<key>/notebooks/<name>
        files.append(
            File(
                f"notebooks/{notebook.name}",
                str(done.parents[1]),
                config["site_dir"],
                config["use_directory_urls"],
            )
        )
    for uri, content in reference_pages().items():
        generated(uri, content)
    for uri, content in listings().items():
        generated(uri, content)
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    src = page.file.src_uri
    if src.endswith(".ipynb"):
        return markdown
    return link_names(site_links(markdown, src))


if __name__ == "__main__":  # make api
    (ROOT / "docs" / "api.md").write_text(api_overview(), encoding="utf-8")
