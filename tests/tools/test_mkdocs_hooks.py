"""tools/mkdocs_hooks.py: a page shown from outside docs/ (hardware/README.md, ...) keeps its links into
docs/ working in the site, where that page sits beside docs/'s pages rather than one level up."""

from __future__ import annotations

from types import SimpleNamespace

from tools import mkdocs_hooks

ROOT = mkdocs_hooks.ROOT
CONFIG = {"docs_dir": str(ROOT / "docs")}


def _page(path: str) -> SimpleNamespace:
    return SimpleNamespace(file=SimpleNamespace(abs_src_path=str(ROOT / path), src_uri=path))


def test_a_shared_page_s_links_into_docs_point_where_the_site_has_them():
    text = ("[v](../docs/validation.md#each-build) [b](bom.md#accuracy) [w](https://example.org/docs/x.md) "
            "[a](../ARCHITECTURE.md) [c](../docs/reference/cli.md)")
    out = mkdocs_hooks.on_page_markdown(text, _page("hardware/README.md"), CONFIG)
    assert out == ("[v](../validation.md#each-build) [b](bom.md#accuracy) [w](https://example.org/docs/x.md) "
                   "[a](../ARCHITECTURE.md) [c](../reference/cli.md)")
    top = mkdocs_hooks.on_page_markdown("[v](docs/validation.md)", _page("ARCHITECTURE.md"), CONFIG)
    assert top == "[v](validation.md)"


def test_a_page_in_docs_is_left_as_written():
    text = "[v](validation.md#each-build) [h](hardware/bom.md)"
    assert mkdocs_hooks.on_page_markdown(text, _page("docs/index.md"), CONFIG) == text
