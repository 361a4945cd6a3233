"""MkDocs hooks: the site shows documents that live beside what they describe, without copying them.

hardware/ (the build guide, the generated BOM, wiring and register map, the pictures), maps/README.md
(how maps are built and checked) and ARCHITECTURE.md stay where they are, next to the files they
describe and readable on a code host; this hook adds them to the site's files under the same relative
paths, so `mkdocs.yml`'s nav names them as `hardware/README.md` etc. and their relative links work.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
SHARED = ("hardware/*.md", "hardware/img/*.png", "hardware/img/*.svg", "maps/README.md", "ARCHITECTURE.md")


def on_files(files: Files, config: Any, **_: Any) -> Files:
    for pattern in SHARED:
        for path in sorted(ROOT.glob(pattern)):
            files.append(File(path.relative_to(ROOT).as_posix(), src_dir=str(ROOT), dest_dir=config["site_dir"],
                              use_directory_urls=config["use_directory_urls"]))
    return files
