"""MkDocs hooks: the site shows documents that live beside what they describe, without copying them.

hardware/ (the build guide, the generated BOM, wiring and register map, the pictures), maps/README.md
(how maps are built and checked) and ARCHITECTURE.md stay where they are, next to the files they
describe and readable on a code host; this hook adds them to the site's files under the same relative
paths, so `mkdocs.yml`'s nav names them as `hardware/README.md` etc. and their relative links work. A link
from one of them into docs/ (e.g. `../docs/validation.md`, right on a code host) is rewritten to where that
page is in the site.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)\s]*)?\)")
SHARED = ("hardware/*.md", "hardware/img/*.png", "hardware/img/*.svg", "maps/README.md", "ARCHITECTURE.md")


def on_files(files: Files, config: Any, **_: Any) -> Files:
    for pattern in SHARED:
        for path in sorted(ROOT.glob(pattern)):
            files.append(File(path.relative_to(ROOT).as_posix(), src_dir=str(ROOT), dest_dir=config["site_dir"],
                              use_directory_urls=config["use_directory_urls"]))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, **_: Any) -> str:
    src, docs = Path(page.file.abs_src_path).resolve(), Path(config["docs_dir"]).resolve()
    if src.is_relative_to(docs):
        return markdown

    def into_docs(match: re.Match[str]) -> str:
        path, anchor = match.group(1), match.group(2) or ""
        target = (src.parent / path).resolve()
        if "://" in path or not target.is_relative_to(docs):
            return match.group(0)
        here = posixpath.dirname(page.file.src_uri) or "."
        return f"]({posixpath.relpath(target.relative_to(docs).as_posix(), here)}{anchor})"

    return LINK.sub(into_docs, markdown)
