"""The documentation site (``make docs``: mkdocs.yml, docs/_site/): the reference covers every
public module and name, the guides name only what exists and link it, the README stays a
landing page. The build itself, its links and its pages as a browser shows them: slow set."""

import os
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_site"))
hooks = pytest.importorskip("hooks", reason="the docs extra (mkdocs) is not installed")
griffe_roles = pytest.importorskip("griffe_roles")

GUIDES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def nav_entries() -> list[str]:
    """The pages mkdocs.yml's nav lists (its !!python tags read as nothing)."""

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_multi_constructor("tag:yaml.org,2002:python/", lambda *a: None)
    nav = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=Loader)["nav"]
    out: list[str] = []

    def walk(item):
        if isinstance(item, str):
            out.append(item)
        elif isinstance(item, dict):
            for v in item.values():
                walk(v)
        elif isinstance(item, list):
            for v in item:
                walk(v)

    walk(nav)
    return out


def test_readme_is_a_landing_page():
    """At most 150 lines, and no paragraph (or list item) over 6 lines outside code and
    tables."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150
    run, fence, longest = 0, False, (0, 0)
    for i, line in enumerate(lines, 1):
        if line.startswith("```"):
            fence, run = not fence, 0
        elif fence or not line.strip() or line.startswith("|"):
            run = 0
        else:
            run = 1 if line.startswith("- ") else run + 1
            longest = max(longest, (run, i))
    assert longest[0] <= 6, (
        f"README.md: a paragraph of {longest[0]} lines ends at line {longest[1]}"
    )


def test_every_public_module_has_a_reference_entry_on_a_page_in_the_nav():
    pages = hooks.reference_pages()
    rendered = {m for text in pages.values() for m in re.findall(r"^::: (\S+)$", text, re.M)}
    import pkgutil

    import gpg

    imported = {
        m.name
        for m in pkgutil.walk_packages(gpg.__path__, "gpg.")
        if not any(p.startswith("_") for p in m.name.split("."))
    }
    imported -= {m for m in imported if m.startswith(hooks.DEPRECATED)}
    assert rendered == imported | {"gpg"}
    assert set(pages) <= set(nav_entries())


def test_the_api_overview_is_current():
    """docs/api.md is generated from the packages' __all__ (``make api``)."""
    assert (ROOT / "docs" / "api.md").read_text(encoding="utf-8") == hooks.api_overview(), (
        "docs/api.md is stale: run `make api`"
    )


def test_every_exported_name_has_an_entry():
    """gpg.__all__ and each package's __all__ (re-exports included) resolve to a documented
    object: what a guide writes as ``gpg.data.from_csv`` links to it."""
    import importlib

    names = hooks.identifiers()
    for module in hooks.public_modules():
        exports = getattr(importlib.import_module(module), "__all__", ())
        missing = [n for n in exports if f"{module}.{n}" not in names and n != "__version__"]
        assert not missing, f"{module}.__all__ without a reference entry: {missing}"
    assert names["Surrogate.predict"] == "gpg.surrogate.Surrogate.predict"
    assert names["gpg.data.from_csv"] == "gpg.data.dataset.from_csv"


def test_every_guide_page_is_in_the_nav():
    nav = set(nav_entries())
    pages = {p.name for p in GUIDES[1:]} - {"README.md"}  # docs/README.md: GitHub's contents
    assert pages <= nav, sorted(pages - nav)


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: p.name)
def test_guides_name_only_what_exists(page):
    """A code span ``gpg.x.y`` (or ``Surrogate.x``) in a guide names a public object of the
    reference: a renamed or removed function fails here, not on a reader."""
    names, fence, stale = hooks.identifiers(), False, set()
    for line in page.read_text().splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
        if fence:
            continue
        for m in re.finditer(r"`((?:gpg|Surrogate|ExactGP|Prediction)\.[A-Za-z][\w.]*)", line):
            name = m.group(1).rstrip(".")
            private = any(part.startswith("_") for part in name.split("."))  # design notes
            if name not in names and not private:
                stale.add(name)
    assert not stale, f"{page.name} names objects that do not exist: {sorted(stale)}"


def test_names_in_code_spans_link_to_the_reference_once_a_page():
    md = "\n".join(
        [
            "# `gpg.data.from_csv` in a heading stays",
            "Call `gpg.data.from_csv(path, columns)` then `Surrogate.predict` and",
            "`gpg.data.from_csv` again; `not.a.name` and `predict` stay code.",
            "```python",
            "`gpg.data.from_csv`",
            "```",
            "[`Surrogate.fit`](elsewhere.md) is a link already.",
        ]
    )
    out = hooks.link_names(md).splitlines()
    assert out[0] == "# `gpg.data.from_csv` in a heading stays"
    assert out[1] == (
        "Call [`gpg.data.from_csv(path, columns)`][gpg.data.dataset.from_csv] then "
        "[`Surrogate.predict`][gpg.surrogate.Surrogate.predict] and"
    )
    assert out[2] == "`gpg.data.from_csv` again; `not.a.name` and `predict` stay code."
    assert out[4] == "`gpg.data.from_csv`"
    assert out[6] == "[`Surrogate.fit`](elsewhere.md) is a link already."


def test_links_written_for_github_are_rewritten_for_the_site():
    readme = "[a](docs/loop.md#x) [b](examples/c_flight/README.md) [c](https://x.org/docs/y)"
    assert hooks.site_links(readme, "index.md") == (
        "[a](loop.md#x) [b](examples/c_flight/README.md) [c](https://x.org/docs/y)"
    )
    page = "[r](../README.md#results) [c](README.md) [e](../examples/c_flight/README.md)"
    page += " [d](results/active/)"
    assert hooks.site_links(page, "loop.md") == (
        "[r](index.md#results) [c](index.md) [e](examples/c_flight/README.md)"
        " [d](results/active/index.md)"
    )


def test_sphinx_roles_in_docstrings_resolve_from_their_scope():
    surrogate = hooks.lookup("gpg.surrogate.Surrogate.predict")
    assert griffe_roles.resolve(surrogate, "Surrogate") == "gpg.surrogate.Surrogate"
    assert griffe_roles.resolve(surrogate, "gpg.gp.kernels") == "gpg.gp.kernels"
    assert griffe_roles.resolve(surrogate, "jax.jit") is None


# ---------------------------------------------------------------------------------------------
# The built site (slow: the notebooks run on a first build, about 4 minutes)


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links: list[str] = []
        self.ids: set[str] = set()
        self.entries = 0
        self.images = 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            self.ids.add(a["id"])
        if tag == "a" and a.get("href"):
            self.links.append(a["href"])
        if "doc-heading" in (a.get("class") or ""):
            self.entries += 1
        if tag == "img":
            self.images += 1


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    if shutil.which("mkdocs", path=str(Path(sys.executable).parent)) is None:
        pytest.skip("mkdocs is not installed (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("site")
    res = subprocess.run(
        [str(Path(sys.executable).parent / "mkdocs"), "build", "--strict", "-d", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert res.returncode == 0, res.stderr[-4000:]
    return out


@pytest.mark.slow
def test_site_builds_with_no_broken_internal_link_and_no_empty_api_page(site):
    pages = {p: _Page() for p in site.rglob("*.html")}
    for path, parser in pages.items():
        parser.feed(path.read_text(encoding="utf-8"))
    broken = []
    for path, parser in pages.items():
        for href in parser.links:
            parts = urlsplit(href)
            if parts.scheme or parts.netloc or href.startswith("mailto:"):
                continue
            # 404.html links from the site's root: it is served at any depth.
            base = site if parts.path.startswith("/") else path.parent
            dest = (base / unquote(parts.path).lstrip("/")).resolve() if parts.path else path
            if dest.is_dir():
                dest = dest / "index.html"
            if not dest.exists():
                broken.append(f"{path.relative_to(site)} -> {href}")
            elif parts.fragment and dest.suffix == ".html":
                if unquote(parts.fragment) not in pages[dest].ids:
                    broken.append(f"{path.relative_to(site)} -> {href} (no such anchor)")
    assert not broken, broken[:20]
    for page in hooks.reference_pages():
        html = site / page.removesuffix(".md") / "index.html"
        assert pages[html].entries >= 2, f"{page}: empty"
    for notebook in (ROOT / "notebooks").glob("*.ipynb"):
        html = site / "notebooks" / notebook.stem / "index.html"
        assert html.exists(), notebook.name
    figure = pages[site / "notebooks" / "01_dataset_exploration" / "index.html"]
    assert figure.images >= 1, "the executed notebook shows no figure"


@pytest.mark.slow
def test_landing_page_renders_in_chromium(site, tmp_path):
    """As a person sees it: headless Chromium renders the landing page, not a blank one."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("Chromium is not installed (Debian: apt install chromium)")
    import numpy as np
    from matplotlib.image import imread

    shot = tmp_path / "index.png"
    subprocess.run(
        [
            chromium,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={tmp_path / 'profile'}",
            "--window-size=1200,1600",
            f"--screenshot={shot}",
            (site / "index.html").as_uri(),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    pixels = imread(shot)[..., :3]
    # Text, the header bar and the table: a blank or unstyled page has almost one colour.
    assert np.mean(np.any(pixels < 0.9, axis=-1)) > 0.03
    assert np.unique((pixels * 15).round().reshape(-1, 3), axis=0).shape[0] > 20
