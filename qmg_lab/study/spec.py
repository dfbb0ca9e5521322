"""A design study's definition: a base configuration, fixed settings, axes over configuration keys and seeds.

    [study]
    name = "virtual_rate"
    base = "../configs/clsf_adev.toml"      # relative to the study file
    seeds = [1, 2]                          # each sets [sim] seed
    storage_level = "study"                 # the points' run files: "study" (summaries) or "full" (raw streams)
    keep_run_files = false                  # keep each point's HDF5 file under DIR/runs/
    [set]                                   # replaces the base's values at every point
    "plan.duration_s" = 2400.0
    [axes]                                  # the grid is the product of the axes; each value replaces the base's
    "dither.virtual_rate_dps" = [2.5, 5.0, 10.0, 20.0]
    "clsf.time_constant_s" = [30.0, 120.0]

A point is one grid cell and one seed; its id ("p0003-s2": grid index, seed) names its result file. Every point
runs on the twins (every instrument's `sim` is set). `expand` builds every point's configuration text and
validates it as `qmg-lab run` would (schema, CLSF stream timing, plan limits) before anything runs.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tomlkit
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from tomlkit.exceptions import ParseError

from qmg_lab.campaign.plan import assert_within_limits, build_plan
from qmg_lab.config.errors import toml_syntax_message
from qmg_lab.config.schema import ConfigError, parse_config, stream_timing_problem
from qmg_lab.instruments import INSTRUMENT_NAMES, LimitError

Scalar = bool | int | float | str


class StudyError(ValueError):
    """A study file or a point of its grid that cannot be used; the message names the point and the field."""


class StudySection(BaseModel):
    """[study]: what to vary is in [axes], what to fix in [set]."""

    model_config = ConfigDict(extra="forbid", strict=True)

    name: str = Field("study", min_length=1, max_length=200)
    base: str = Field(min_length=1, description="base campaign configuration, relative to the study file")
    seeds: list[int] = Field(default_factory=lambda: [1], min_length=1, description="[sim] seed of each repeat")
    storage_level: Literal["study", "full"] = Field("study", description="the points' run files' storage.level")
    keep_run_files: bool = Field(False, description="keep each point's run file under DIR/runs/")


class StudyFile(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)

    study: StudySection
    set: dict[str, Scalar | list[Scalar]] = Field(default_factory=dict)
    axes: dict[str, list[Scalar]] = Field(default_factory=dict)


@dataclass(frozen=True)
class Point:
    """One campaign of the study: a grid cell (`index`, its axis values) and a seed."""

    index: int
    seed: int
    axes: dict[str, Scalar]
    config_text: str

    @property
    def id(self) -> str:
        return f"p{self.index:04d}-s{self.seed}"

    def describe(self) -> str:
        values = ", ".join(f"{k} = {v!r}" for k, v in self.axes.items())
        return f"point {self.id} ({values}{', ' if values else ''}seed {self.seed})"


@dataclass(frozen=True)
class Study:
    """A loaded study: its definition and every point, validated."""

    path: Path
    spec: StudyFile
    points: list[Point]

    @property
    def axis_names(self) -> list[str]:
        return list(self.spec.axes)

    def fingerprint(self) -> str:
        """SHA-256 over every point's id and configuration text: what `--resume` checks a directory against."""
        h = hashlib.sha256()
        for p in self.points:
            h.update(p.id.encode())
            h.update(p.config_text.encode())
        h.update(json.dumps([self.spec.study.storage_level, self.spec.study.keep_run_files]).encode())
        return h.hexdigest()


def _set_key(doc: dict[str, Any], key: str, value: Scalar | list[Scalar], where: str) -> None:
    """doc[section][...][name] = value for a dotted key "section.name"; the schema checks the name later."""
    parts = key.split(".")
    if len(parts) < 2 or not all(parts):
        raise StudyError(f"{where}: {key!r} is not a configuration key (write section.key, e.g. dither.frequency_hz)")
    node = doc
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise StudyError(f"{where}: {key!r}: {part} is a value, not a section")
        node = child
    node[parts[-1]] = value


def load_study(path: str | Path) -> Study:
    """Read a study file and its base, build every point's configuration and validate them all.

    Raises StudyError naming the file, or each point that fails and the field (every failing point, not only
    the first)."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise StudyError(f"{p}: study file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise StudyError(f"{p}: cannot read the study file: {exc}") from None
    raw = _toml(text, str(p))
    try:
        spec = StudyFile.model_validate(raw)
    except ValidationError as exc:
        lines = [f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" for e in exc.errors(include_url=False)]
        raise StudyError(f"{p}: invalid study file:\n  " + "\n  ".join(lines)) from None
    for key, values in spec.axes.items():
        if not values:
            raise StudyError(f"{p}: axis {key!r} has no values")
        if len(set(map(repr, values))) != len(values):
            raise StudyError(f"{p}: axis {key!r} repeats a value: {values}")
    if len(set(spec.study.seeds)) != len(spec.study.seeds):
        raise StudyError(f"{p}: [study] seeds repeats a seed: {spec.study.seeds}")
    for key in spec.axes:
        if key in spec.set:
            raise StudyError(f"{p}: {key!r} is both in [set] and in [axes]")
        if key in ("sim.seed", "storage.level"):
            raise StudyError(f"{p}: {key!r} is set by the study ([study] seeds, storage_level), not an axis")
    base_path = (p.parent / spec.study.base).resolve()
    try:
        base_text = base_path.read_bytes().decode("utf-8")
        _toml(base_text, f"{p}: base configuration {base_path}")  # a syntax error in words, as `check` gives it
        base: dict[str, Any] = tomlkit.parse(base_text)  # keeps the base's comments
    except FileNotFoundError:
        raise StudyError(
            f"{p}: base configuration {base_path} not found ([study] base is relative to the study file)"
        ) from None
    except (OSError, UnicodeDecodeError, ParseError) as exc:
        raise StudyError(f"{p}: base configuration {base_path}: {exc}") from None
    for key, value in spec.set.items():
        _set_key(base, key, value, f"{p} [set]")
    for name in INSTRUMENT_NAMES:  # every point runs each of them on its twin
        _set_key(base, f"{name}.sim", True, str(p))
    _set_key(base, "storage.level", spec.study.storage_level, str(p))
    points, problems = [], []
    grid = list(itertools.product(*spec.axes.values())) if spec.axes else [()]
    for index, combo in enumerate(grid):
        for seed in spec.study.seeds:
            doc = copy.deepcopy(base)
            axes = dict(zip(spec.axes, combo, strict=True))
            for key, value in axes.items():
                _set_key(doc, key, value, f"{p} [axes]")
            _set_key(doc, "sim.seed", seed, str(p))
            point = Point(index=index, seed=seed, axes=axes, config_text=tomlkit.dumps(doc))
            problem = point_problem(point)
            if problem is not None:
                problems.append(f"{point.describe()}: {problem}")
            points.append(point)
    if problems:
        raise StudyError(f"{p}: {len(problems)} of {len(points)} points cannot run:\n  " + "\n  ".join(problems))
    return Study(path=p, spec=spec, points=points)


def _toml(text: str, where: str) -> dict[str, Any]:
    """tomllib.loads; a syntax error is a StudyError in words (qmg_lab/config/errors.py: the line, the key)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise StudyError(f"{where}: not valid TOML: {toml_syntax_message(text, exc)}") from None


def point_problem(point: Point) -> str | None:
    """Why a point's configuration cannot run (schema, CLSF stream timing, plan limits), or None."""
    try:
        cfg = parse_config(point.config_text, "configuration")
    except ConfigError as exc:
        return str(exc).replace("configuration: invalid configuration:\n  ", "").replace("\n  ", "; ")
    problem = stream_timing_problem(cfg)
    if problem is not None:
        return (
            f"CLSF stream timing (lockin.demod_rate_hz = {cfg.lockin.demod_rate_hz:g}, dither.frequency_hz = "
            f"{cfg.dither.frequency_hz:g}): {problem}"
        )
    try:
        assert_within_limits(cfg, build_plan(cfg))
    except LimitError as exc:
        return str(exc)
    return None
