"""The artifact pipeline's stages by name: their files' suffixes, the producer stamp each writes, and the
command that rebuilds one (named wherever a stale child is refused). Below the pipeline, so the files'
readers and writers can name them without reaching up into it."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from trimeter.errors import InputError
from trimeter.paths import MAPS_DIR
from trimeter.version import __version__

STAGES = ("tmap", "tins", "tlut", "onnx")
DEFAULT_STAGES = ("tmap", "tins", "tlut")
SUFFIX = {"tmap": ".tmap", "tins": ".tins", "tlut": ".tlut", "onnx": ".onnx"}


def parse_stages(text: str) -> tuple[str, ...]:
    """'tmap,tins' → the stages in pipeline order; an unknown name is an InputError naming it."""
    names = [s.strip() for s in str(text).split(",") if s.strip()]
    unknown = [s for s in names if s not in STAGES]
    if unknown or not names:
        raise InputError(f"--stages: {unknown[0] if unknown else 'nothing'!r} is not a stage "
                         f"(stages: {', '.join(STAGES)}, comma-separated)")
    return tuple(s for s in STAGES if s in names)


def stage_producer(stage: str) -> dict:
    """The producer stamp of a stage's files."""
    return {"name": f"trimeter map build --stages {stage}", "version": __version__}


class _MapFile(Protocol):
    """What a rebuild command needs of a map (an AppearanceMap, without importing it)."""

    @property
    def name(self) -> str: ...

    @property
    def path(self) -> Path | None: ...


def rebuild_command(amap: _MapFile, stage: str) -> str:
    """The command that rebuilds `stage` of this map in place (the shipped recipe's path when it has one)."""
    recipe = MAPS_DIR / "recipes" / f"{amap.name}.toml"
    recipe_arg = _shown_path(recipe) if recipe.is_file() else "RECIPE.toml"
    out = f" --out {_shown_path(amap.path)}" if amap.path is not None else ""
    return f"trimeter map build {recipe_arg}{out} --stages {stage}"


def _shown_path(path: Path) -> str:
    """Relative to the working directory when inside it (maps/…), else as it is."""
    path = Path(path).absolute()
    return str(path.relative_to(Path.cwd())) if path.is_relative_to(Path.cwd()) else str(path)
