"""The HF2LI node tree of the data-server twin: concrete node paths, their types and their values.

The node *documentation* comes from zhinst-toolkit's bundled ``resources/nodedoc_hf2.json`` (one entry per
generic path such as ``/devxxxx/demods/n/rate``, with type, properties, unit and enumerated options). This module
expands every ``n`` into the instances an HF2LI with the given options (``features/options``; the configuration's
[sim] hf2_options, MF, PLL, PID by default) has and stores a value per leaf. Where each count comes from:

* zhinst-toolkit's recorded HF2 node list (its tests/data/list_nodes_hf2_dev.txt, an HF2LI with MF and PLL and
  without PID): 6 demodulators, 6 oscillators, 2 PLLs, 2 outputs listing mixer channels 0..7 (enables,
  amplitudes, waveforms), 2 inputs, 4 AuxOuts, one AuxIn block of 2 values, and *no* ``pids`` branch: a branch of
  an option the instrument lacks is not listed at all. The twin drops ``plls`` without PLL and ``pids`` without
  PID likewise; with PID it lists 4 PIDs (HF2 user manual, HF2-PID option: 4 PID controllers).
* without MF: 2 oscillators (the public qudi-iqo-modules HF2 driver: "index of oscillator; valid inputs: 0 or
  1") and each output lists only mixer channels 6 and 7 (the same driver's recorded non-MF HF2 dev1492:
  ``{'/dev1492/sigouts/0/enables/6': 0, '/dev1492/sigouts/0/enables/7': 0}``; zhinst-utils
  ``default_output_mixer_channel``: output 1 -> 6, output 2 -> 7 without MF). *Assumed*: amplitudes/waveforms list
  the same channels as enables, and the demodulator count (6) does not depend on MF.
* the ``mods`` branch (2 modulators) only with the MOD option: *inferred* by analogy with ``pids`` (the recorded
  list shows an option's branch absent without the option); ZCTRL and CPU branches as recorded, whatever the
  options.

The nodedoc carries no power-on values; ``POWER_ON`` holds the twin's (documented in docs/wiring.md). A real
HF2 after power-on differs in details; the driver configures every node it relies on, so nothing depends on them.

Set rules implemented (what the real server does with a bad set, as far as documented):
* unknown path -> RuntimeError "ZIAPINotFoundException"; read-only path -> RuntimeError "ZIAPIWriteException";
* Integer nodes are truncated to int; enumerated nodes (except bit-coded ones) reject a value not in their
  options with RuntimeError naming the allowed values; Double nodes take float; String nodes take str.
"""

from __future__ import annotations

import fnmatch
import importlib.util
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

NON_MF_MIXER_CHANNELS = (6, 7)
NON_MF_OSCILLATORS = 2
OUTPUT_MIXER_BRANCHES = ("sigouts/n/enables/n", "sigouts/n/amplitudes/n", "sigouts/n/waveforms/n")

# How many instances each indexed branch has on an HF2LI with MF, PLL and PID options. Key: the generic path
# up to (and including) the ``n`` being expanded, relative to the device. ``instances`` adapts it to the options.
INSTANCE_COUNTS: dict[str, int] = {
    "demods/n": 6,
    "oscs/n": 6,
    "plls/n": 2,
    "pids/n": 4,
    "sigouts/n": 2,
    "sigouts/n/enables/n": 8,
    "sigouts/n/amplitudes/n": 8,
    "sigouts/n/waveforms/n": 8,
    "sigins/n": 2,
    "auxouts/n": 4,
    "auxins/n": 1,
    "mods/n": 2,
    "mods/n/sidebands/n": 2,
    "scopes/n": 1,
    "dios/n": 1,
    "cpus/n": 1,
    "cpus/n/userregs/n": 64,
    "zctrls/n": 2,
    "zctrls/n/tamp/n": 2,
    "status/flags/mixerclip/n": 2,
    "status/flags/adcclip/n": 2,
}

# Power-on values of the twin, by generic relative path (fnmatch on the concrete relative path). First match wins.
POWER_ON: list[tuple[str, Any]] = [
    ("demods/*/rate", 1800.0),
    ("demods/*/order", 4),
    ("demods/*/timeconstant", 0.0101),
    ("demods/*/harmonic", 1),
    ("oscs/*/freq", 100e3),
    ("plls/*/freqcenter", 100e3),
    ("plls/*/freqrange", 1e3),
    ("plls/*/harmonic", 1),
    ("plls/*/order", 4),
    ("plls/*/timeconstant", 1e-3),
    ("plls/*/rate", 1e5),
    ("pids/*/range", 1.0),
    ("pids/*/rate", 1e5),
    ("pids/*/demod/harmonic", 1),
    ("pids/*/demod/order", 4),
    ("pids/*/demod/timeconstant", 0.0101),
    ("pids/*/monitorscale", 1.0),
    ("sigouts/*/range", 1.0),
    ("sigins/*/range", 1.0),
    ("auxouts/*/scale", 1.0),
    ("system/activeinterface", "USB"),
    ("system/hwrevision", 1),
    ("system/properties/minfreq", 0.0),
    ("system/properties/maxfreq", 100e6),
    ("system/properties/negativefreq", 0),
    ("system/properties/freqresolution", 48),
    ("system/properties/mintimeconstant", 780e-9),
    ("system/properties/maxtimeconstant", 500.0),
    ("stats/physical/temp", 45.0),
]

_INT_TYPES = ("Integer", "Integer (enumerated)")


class NodeError(RuntimeError):
    """A node operation the HF2 data server would refuse (message names the node)."""


@dataclass(frozen=True)
class NodeMeta:
    """Documentation of one concrete node."""

    path: str  # absolute, lower case: /dev1234/demods/0/rate
    type: str  # nodedoc type: Integer, Integer (enumerated), Double, String, ZIDemodSample, ...
    readable: bool
    writable: bool
    setting: bool
    stream: bool
    options: tuple[float, ...] | None  # allowed values of an enumerated (non bit-coded) node

    @property
    def is_value(self) -> bool:
        """A node with a scalar value (not a stream or vector)."""
        return self.type in _INT_TYPES or self.type in ("Double", "String")


def nodedoc_path() -> Path:
    """Location of zhinst-toolkit's bundled HF2 node documentation (found without importing toolkit)."""
    spec = importlib.util.find_spec("zhinst.toolkit")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("zhinst-toolkit is not installed: the HF2 twin needs its resources/nodedoc_hf2.json")
    return Path(next(iter(spec.submodule_search_locations))) / "resources" / "nodedoc_hf2.json"


def instances(options: tuple[str, ...]) -> dict[str, tuple[int, ...]]:
    """The indices each indexed branch lists on an HF2LI with ``options`` (module doc)."""
    table = {k: tuple(range(v)) for k, v in INSTANCE_COUNTS.items()}
    if "MF" not in options:
        table["oscs/n"] = tuple(range(NON_MF_OSCILLATORS))
        for branch in OUTPUT_MIXER_BRANCHES:
            table[branch] = NON_MF_MIXER_CHANNELS
    if "PLL" not in options:
        table["plls/n"] = ()
    if "PID" not in options:
        table["pids/n"] = ()
    if "MOD" not in options:
        table["mods/n"] = ()
    return table


def _expand(generic_rel: str, table: dict[str, tuple[int, ...]]) -> list[str]:
    """All concrete relative paths of a generic one: demods/n/rate -> demods/0/rate ... demods/5/rate."""
    parts = generic_rel.split("/")
    out = [""]
    prefix = ""
    for part in parts:
        prefix = f"{prefix}/{part}" if prefix else part
        if part == "n":
            indices = table.get(prefix)
            if indices is None:
                raise KeyError(f"no instance count for {prefix!r} in INSTANCE_COUNTS")
            out = [f"{o}/{i}" if o else str(i) for o in out for i in indices]
        else:
            out = [f"{o}/{part}" if o else part for o in out]
    return out


def _options(entry: dict[str, Any]) -> tuple[float, ...] | None:
    opts = entry.get("Options")
    if not opts or entry.get("Unit") == "bit-coded" or "enumerated" not in entry.get("Type", ""):
        return None
    try:
        return tuple(sorted(float(k) for k in opts))
    except ValueError:
        return None


def _power_on(rel: str, meta: NodeMeta) -> Any:
    for pattern, value in POWER_ON:
        if fnmatch.fnmatchcase(rel, pattern):
            return value
    if meta.type == "String":
        return ""
    if meta.type == "Double":
        return 0.0
    return 0


class HF2NodeTree:
    """Concrete node documentation and values of one HF2LI. Paths are absolute and case-insensitive."""

    def __init__(self, device_id: str, clockbase_hz: float, options: tuple[str, ...]) -> None:
        if not re.fullmatch(r"dev\d+", device_id.lower()):
            raise ValueError(f"device_id {device_id!r} must look like 'dev1234'")
        self.device_id = device_id.lower()
        self.options = tuple(o.upper() for o in options)
        self.instances = instances(self.options)
        self._prefix = f"/{self.device_id}/"
        doc = json.loads(nodedoc_path().read_text(encoding="utf-8"))
        self.meta: dict[str, NodeMeta] = {}
        self.values: dict[str, Any] = {}
        for generic, entry in doc.items():
            rel_generic = generic.lower().split("/", 2)[2]  # drop "/devxxxx/"
            props = entry.get("Properties", "")
            for rel in _expand(rel_generic, self.instances):
                path = f"/{self.device_id}/{rel}"
                meta = NodeMeta(
                    path=path,
                    type=entry["Type"],
                    readable="Read" in props,
                    writable="Write" in props,
                    setting="Setting" in props,
                    stream="Stream" in props,
                    options=_options(entry),
                )
                self.meta[path] = meta
                if meta.is_value:
                    self.values[path] = _power_on(rel, meta)
        self.poke("clockbase", int(round(clockbase_hz)))
        self.poke("features/devtype", "HF2LI")
        self.poke("features/serial", self.device_id.upper())
        self.poke("features/options", "\n".join(self.options))  # "newline-separated list" (nodedoc)
        self.poke("system/properties/timebase", 1.0 / clockbase_hz)
        for n in self.instances["plls/n"]:
            # Each PLL writes the oscillator and uses the demodulator of its own index. *Assumed*: both nodes are
            # read-only ("Index of the oscillator used", "Source demodulator", nodedoc_hf2.json) and the HF2 user
            # manual's PLL tab maps "the frequency of an external signal ... onto one of the instrument's internal
            # oscillators" without naming which; the driver reads plls/n/oscselect, it never assumes this value.
            self.poke(f"plls/{n}/oscselect", n)
            self.poke(f"plls/{n}/demodselect", n)
        for n in self.instances["auxouts/n"]:
            self.poke(f"auxouts/{n}/outputselect", n)  # X, Y, R, Theta of demod 0: not under PID control

    @property
    def n_oscillators(self) -> int:
        return len(self.instances["oscs/n"])

    def has(self, rel_or_abs: str) -> bool:
        """Whether the instrument lists this node (twin-internal; lower-case path)."""
        return (rel_or_abs if rel_or_abs[0] == "/" else self._prefix + rel_or_abs) in self.meta

    # ------------------------------------------------------------------ paths
    def absolute(self, path: str) -> str:
        """Lower-case absolute path; a relative path is taken relative to the device."""
        p = path.strip().lower()
        return p if p.startswith("/") else f"/{self.device_id}/{p}"

    def resolve(self, pattern: str) -> list[str]:
        """Concrete paths matching a path, a branch (all leaves below it) or a '*' wildcard pattern."""
        p = self.absolute(pattern).rstrip("/")
        if p in self.meta:
            return [p]
        if any(c in p for c in "*?["):
            hits = [k for k in self.meta if fnmatch.fnmatchcase(k, p) or fnmatch.fnmatchcase(k, p + "/*")]
        else:
            hits = [k for k in self.meta if k.startswith(p + "/")]
        return hits

    def meta_of(self, path: str) -> NodeMeta:
        p = self.absolute(path)
        try:
            return self.meta[p]
        except KeyError:
            raise NodeError(f"ZIAPINotFoundException: node {p} does not exist") from None

    # ------------------------------------------------------------------ values
    def read(self, path: str) -> Any:
        meta = self.meta_of(path)
        if not meta.readable or not meta.is_value:
            raise NodeError(f"ZIAPIReadException: node {meta.path} cannot be read as a value")
        return self.values[meta.path]

    def coerce(self, path: str, value: Any) -> tuple[str, Any]:
        """Validate a client write: (absolute path, value as stored). Raises NodeError like the server."""
        meta = self.meta_of(path)
        if not meta.writable:
            raise NodeError(f"ZIAPIWriteException: node {meta.path} is read-only")
        if meta.type in _INT_TYPES:
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise NodeError(f"node {meta.path} needs a number, got {value!r}") from None
            if meta.options is not None and number not in meta.options:
                allowed = ", ".join(f"{o:g}" for o in meta.options)
                raise NodeError(f"node {meta.path}: value {value!r} is not one of {allowed}")
            stored: Any = number if number != int(number) else int(number)
        elif meta.type == "Double":
            try:
                stored = float(value)
            except (TypeError, ValueError):
                raise NodeError(f"node {meta.path} needs a number, got {value!r}") from None
        elif meta.type == "String":
            stored = str(value)
        else:
            raise NodeError(f"ZIAPIWriteException: node {meta.path} of type {meta.type} cannot be set")
        return meta.path, stored

    def poke(self, rel_or_abs: str, value: Any) -> None:
        """Twin-internal write (read-only nodes included, no validation). Paths in lower case."""
        self.values[rel_or_abs if rel_or_abs[0] == "/" else self._prefix + rel_or_abs] = value

    def peek(self, rel_or_abs: str) -> Any:
        """Twin-internal read. Paths in lower case."""
        return self.values[rel_or_abs if rel_or_abs[0] == "/" else self._prefix + rel_or_abs]

    def list(
        self,
        pattern: str,
        *,
        settings_only: bool = False,
        streaming_only: bool = False,
        exclude_streaming: bool = False,
    ) -> list[str]:
        """Upper-case leaf paths like the server's listNodes(recursive, leavesonly), optionally filtered."""
        hits = self.resolve(pattern)
        out = []
        for p in hits:
            m = self.meta[p]
            if settings_only and not m.setting:
                continue
            if streaming_only and not m.stream:
                continue
            if exclude_streaming and m.stream:
                continue
            out.append(p.upper())
        return out
