"""grainpipe from Python: run pipelines that build digital twins of granular materials.

The stages, registry, engine and cache are those of the ``pipe`` command (the compiled
``grainpipe._native`` module); this package only wraps the results for numpy, xarray,
pandas and pyvista. See docs/python.md.

    import grainpipe as gp
    r = gp.run("pipelines/spheres.yaml", set={"pack.volume_fraction": 0.25}, seed=1)
    img = r["voxels.image"]          # an Image: img.array is numpy, shape (z, y, x)
"""

from __future__ import annotations

import json
import operator
import os
import warnings
from typing import Any, Callable, Iterable, Mapping, Optional, Union

from . import _native
from ._native import GrainpipeError, PipelineError, StageError
from ._results import (
    Artifact,
    ClumpLibrary,
    Collection,
    ContactGraph,
    Field,
    Image,
    Packing,
    Result,
    Series,
    Table,
    Tensor,
)

__version__ = _native.VERSION

__all__ = [
    "run",
    "validate",
    "stages",
    "describe",
    "GrainpipeError",
    "PipelineError",
    "StageError",
    "Result",
    "Artifact",
    "Image",
    "Field",
    "Packing",
    "ClumpLibrary",
    "ContactGraph",
    "Table",
    "Tensor",
    "Series",
    "Collection",
]

Pipeline = Union[str, "os.PathLike[str]", Mapping[str, Any]]

#: The name errors and provenance give a pipeline passed as a dict or as YAML text.
PSEUDO_PATH = "<python>"


def _plain(value: Any) -> Any:
    """JSON for what json cannot write itself: numpy scalars (``np.float32(0.3)``,
    ``np.int64(4)``) as their Python value and numpy arrays as lists, both through
    ``.tolist()``/``.item()``, so values computed with numpy pass as parameters."""
    for method in ("tolist", "item"):
        convert = getattr(value, method, None)
        if callable(convert) and hasattr(value, "dtype"):
            return convert()
    raise TypeError(f"{type(value).__name__} is not a parameter value (give a number, text, "
                    "a list or a dict)")


def _json(value: Any, **kw: Any) -> str:
    return json.dumps(value, default=_plain, **kw)


def _targets(targets: Optional[Iterable[str]]) -> list[str]:
    """Step ids; one id given as a string is one target (``list("dem")`` would be three)."""
    if targets is None:
        return []
    if isinstance(targets, str):
        return [targets]
    out = list(targets)
    for t in out:
        if not isinstance(t, str):
            raise TypeError(f"targets must be step ids (strings), got {t!r}")
    return out


def _source(pipeline: Pipeline) -> tuple[str, bool]:
    """(path or YAML text, is_text). A dict is written as JSON, which is valid YAML, so the
    same parser (and its error locations) applies."""
    if isinstance(pipeline, Mapping):
        return _json(pipeline, indent=2), True
    if isinstance(pipeline, os.PathLike):
        return os.fspath(pipeline), False
    if isinstance(pipeline, str):
        # YAML text has a newline or a mapping colon; a path has neither.
        if "\n" in pipeline or ("stages:" in pipeline):
            return pipeline, True
        return pipeline, False
    raise TypeError(f"pipeline must be a path, YAML text or a dict, not {type(pipeline).__name__}")


def _overrides(set: Optional[Mapping[str, Any]]) -> list[str]:
    """`{"pack.volume_fraction": 0.25}` -> `["pack.volume_fraction=0.25"]`, as `pipe --set`.
    Strings pass as written (so units such as "25 um" work); other values as JSON (YAML)."""
    out = []
    for key, value in (set or {}).items():
        text = value if isinstance(value, str) else _json(value)
        out.append(f"{key}={text}")
    return out


def _progress_callback(progress: Any) -> Optional[Callable[[dict], None]]:
    """The callable given, a tqdm-based display (progress=None/True, when tqdm is
    installed), or None. Warnings from stages become Python warnings either way."""
    if callable(progress):
        user = progress

        def relay(event: dict) -> None:
            if event["event"] == "message" and event["level"] == "warn":
                warnings.warn(f"{event['step']}: {event['text']}", stacklevel=3)
            user(event)

        return relay
    if progress is False:

        def warn_only(event: dict) -> None:
            if event["event"] == "message" and event["level"] == "warn":
                warnings.warn(f"{event['step']}: {event['text']}", stacklevel=3)

        return warn_only
    try:
        from tqdm.auto import tqdm  # optional: a bar per step in Jupyter or a terminal
    except ImportError:
        return _progress_callback(False)
    bars: dict[str, Any] = {}

    def show(event: dict) -> None:
        kind = event["event"]
        step = event.get("step")
        if kind == "start":
            bars[step] = tqdm(
                desc=f"[{event['index'] + 1}/{event['count']}] {step} ({event['stage']})",
                total=None,
                leave=True,
            )
        elif kind == "progress" and step in bars:
            bar = bars[step]
            done, total = event["done"], event["total"]
            # A bar never moves back (as `pipe`'s): a report behind the shown fraction, or one
            # with a new total, keeps at least the fraction already shown.
            if total and bar.total and total != bar.total:
                done = max(done, -(-bar.n * total // bar.total))
            elif not total or total == bar.total:
                done = max(done, bar.n)
            if total and bar.total != total:
                bar.total = total
            bar.n = min(done, total) if total else done
            bar.refresh()
        elif kind == "finish" and step in bars:
            bar = bars.pop(step)
            if bar.total:
                bar.n = bar.total
            bar.set_postfix_str("cached" if event["from_cache"] else f"{event['wall_s']:.2f} s")
            bar.close()
        elif kind == "message":
            if event["level"] == "warn":
                warnings.warn(f"{step}: {event['text']}", stacklevel=3)
            else:
                tqdm.write(f"{step}: {event['text']}")

    return show


def run(
    pipeline: Pipeline,
    *,
    set: Optional[Mapping[str, Any]] = None,
    seed: Optional[int] = None,
    targets: Optional[Iterable[str]] = None,
    cache: Union[bool, str, "os.PathLike[str]"] = True,
    exports: bool = True,
    out: Optional[Union[str, "os.PathLike[str]"]] = None,
    progress: Any = None,
    plugin_dirs: Iterable[Union[str, "os.PathLike[str]"]] = (),
    allow_plugins: bool = False,
) -> Result:
    """Runs a pipeline as ``pipe run`` does and returns its results.

    pipeline: a YAML file path, YAML text, or a dict with the same structure.
    set: parameter overrides ``{"step.key": value}`` (``pipe run --set``); strings may carry
        units ("25 um").
    seed: overrides the pipeline's seed. targets: a step id or a list of them: only these
        steps and the steps they need run, and only their exports are written (``pipe run
        --target``). cache: True (``.grainpipe-cache``), False, or a cache directory.
    exports: write the pipeline's ``export:`` files (default, like ``pipe run``); with False
        nothing is written and every step (or just ``targets``) is computed.
    out: move the exports into this directory (``pipe run --out``).
    progress: None/True shows tqdm bars when tqdm is installed; False shows nothing; a
        callable receives event dicts (``event``: start, progress, message, finish,
        exported). An exception raised by the callable cancels the run and propagates.
    plugin_dirs: plugin libraries or directories (``--plugin-dir``); allow_plugins trusts the
        libraries a pipeline's ``plugins:`` names (``--allow-plugins``).

    Ctrl-C (KeyboardInterrupt) stops the running stage at its next checkpoint and raises
    KeyboardInterrupt; exports are written atomically, so none is left half-written.
    Raises PipelineError (bad input, nothing ran) or StageError (a stage failed).
    """
    source, is_text = _source(pipeline)
    if cache is True:
        cache_dir: Optional[str] = ".grainpipe-cache"
    elif cache is False or cache is None:
        cache_dir = None
    else:
        cache_dir = os.fspath(cache)
    raw = _native.run(
        source,
        is_text,
        PSEUDO_PATH,
        _overrides(set),
        None if seed is None else operator.index(seed),
        _targets(targets),
        exports,
        None if out is None else os.fspath(out),
        [os.fspath(p) for p in plugin_dirs],
        allow_plugins,
        cache_dir,
        _progress_callback(progress),
    )
    return Result(raw)


def validate(
    pipeline: Pipeline,
    *,
    set: Optional[Mapping[str, Any]] = None,
    seed: Optional[int] = None,
    targets: Optional[Iterable[str]] = None,
    exports: bool = True,
    out: Optional[Union[str, "os.PathLike[str]"]] = None,
    plugin_dirs: Iterable[Union[str, "os.PathLike[str]"]] = (),
    allow_plugins: bool = False,
) -> dict:
    """Checks and plans a pipeline without running it (``pipe validate``).

    Returns a dict: ``steps`` (in run order: id, stage, memory_bytes, params, and per output
    port the announced kind, grid, counts and box), ``exports``, ``memory_bytes`` (the
    estimate for the whole run), ``seed``. Raises PipelineError as ``run`` does.
    """
    source, is_text = _source(pipeline)
    return _native.validate(
        source,
        is_text,
        PSEUDO_PATH,
        _overrides(set),
        None if seed is None else operator.index(seed),
        _targets(targets),
        exports,
        None if out is None else os.fspath(out),
        [os.fspath(p) for p in plugin_dirs],
        allow_plugins,
    )


def stages(plugin_dirs: Iterable[Union[str, "os.PathLike[str]"]] = ()) -> dict:
    """Every stage's description by id (as ``gp.describe``), plugins' stages included."""
    reg = _native.registry_description([os.fspath(p) for p in plugin_dirs])
    return {s["id"]: s for s in reg["stages"]}


def export_formats() -> list:
    """The export formats (name, extensions, doc)."""
    return _native.registry_description([])["export_formats"]


def describe(stage: str, plugin_dirs: Iterable[Union[str, "os.PathLike[str]"]] = ()) -> dict:
    """A stage's description, the one ``pipe describe --json STAGE`` prints: ``params`` (name,
    type, unit, default, doc, ...), ``inputs`` and ``outputs`` (ports with kinds),
    ``with_schema`` (JSON Schema of its ``with:``). Raises PipelineError for an unknown id,
    with a suggestion."""
    return _native.describe_stage(stage, [os.fspath(p) for p in plugin_dirs])
