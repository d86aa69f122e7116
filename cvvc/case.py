"""Case files: ``cvvc init case.toml`` writes one, ``cvvc run case.toml`` reads it, flags override it.

The tree itself (sections, fields, defaults, descriptions) is ``schemas.settings.RunCase``; this module only turns it
into commented TOML (:func:`case_toml`, generated from the tree so it never drifts), decodes a file into it
(:func:`load_case`: unknown keys refused naming the key, paths relative to the file's folder) and lays the
command line's flags over it (:func:`apply_flags`, the one table :data:`RUN_FLAGS`). docs/case-file.md.
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import msgspec

from cvvc.errors import CommandError
from schemas.settings import SECTIONS, AgentOptions, RunCase

__all__ = ["AGENT_FLAGS", "PATH_KEYS", "RUN_FLAGS", "CaseFileError", "absolute_paths", "agent_options_from_args",
           "apply_flags", "case_toml", "load_case", "write_case"]


class CaseFileError(CommandError):
    """A case file that cannot be read or decoded, or a flag that makes the case invalid; the message names the key."""


#: The keys of a case file that are paths, as (section, key) (``None``: the top level); relative to the file's folder.
PATH_KEYS: tuple[tuple[str | None, str], ...] = (
    (None, "cache"), ("feeder", "map"), ("feeder", "model"), ("output", "out"), ("security", "ca_dir"))


def _given(value: object) -> bool:
    return value is not None and value is not False  # store_true flags are False when not given


def _true(value: object) -> object:
    return True


def _false(value: object) -> object:
    return False


def _same(value: object) -> object:
    return value


#: ``cvvc run``'s flags (argparse ``dest``) -> (section or None for the top level, key, the setting of the flag's
#: value). A flag overrides the file only when given (not None; a store_true flag when set).
RUN_FLAGS: Mapping[str, tuple[str | None, str, Callable[[Any], object]]] = MappingProxyType({
    "case": (None, "case", _same),
    "cache": (None, "cache", _same),
    "feeder": ("feeder", "map", _same),
    "model": ("feeder", "model", _same),
    "train_seed": ("feeder", "train_seed", _same),
    "start": ("window", "start", _same),
    "days": ("window", "days", _same),
    "year_seed": ("window", "year_seed", _same),
    "bandwidth_v": ("agent", "bandwidth_v120", _same),
    "pv_margin_window_s": ("agent", "pv_margin_window_s", _same),
    "setpoint_hold": ("agent", "setpoint_hold", _true),
    "control_banks": ("agent", "control_banks", _true),
    "realtime": ("bridge", "realtime", _true),
    "speed": ("bridge", "speed", _same),
    "lockstep_timeout_s": ("bridge", "lockstep_timeout_s", _same),
    "noise_pmu_pct": ("bridge", "noise_pmu_pct", _same),
    "noise_scada_pct": ("bridge", "noise_scada_pct", _same),
    "drop_prob": ("bridge", "drop_prob", _same),
    "drop_burst_min": ("bridge", "drop_burst_min", _same),
    "meas_delay_s": ("bridge", "meas_delay_s", _same),
    "clock_skew_s": ("bridge", "clock_skew_s", _same),
    "pv_protocol": ("bridge", "pv_protocol", _same),
    "field_protocol": ("bridge", "field_protocol", _same),
    "out": ("output", "out", _same),
    "no_record": ("output", "record", _false),
    "no_baseline": ("output", "baseline", _false),
    "insecure": ("security", "secure", _false),
    "secure": ("security", "secure", _true),
    "ca_dir": ("security", "ca_dir", _same),
})

#: The agent settings that have flags of their own (``cvvc.cli_options``) and, in campaign files of old, keys of a
#: variant's own (``cvvc.campaign``).
AGENT_FLAGS = ("pv_margin_window_s", "setpoint_hold", "control_banks")


def _where(error: Exception) -> str:
    """The decoder's error as one line naming the key (``agent.foo``) the way a case file writes it."""
    text = str(error)
    unknown = re.fullmatch(r"Object contains unknown field `([^`]+)`(?: - at `\$\.?([^`]*)`)?", text)
    if unknown:
        key = ".".join(k for k in (unknown.group(2), unknown.group(1)) if k)
        return f"unknown key {key!r} (`cvvc init case.toml` writes every key there is)"
    return re.sub(r" - at `\$\.?(.*)`$", lambda m: f" (key {m.group(1)!r})" if m.group(1) else "", text)


def _check(case: RunCase, what: str) -> RunCase:
    """``case`` with its constraints checked (they run on decode only), or ``CaseFileError`` naming the key."""
    try:
        return msgspec.convert(msgspec.to_builtins(case), RunCase)
    except msgspec.ValidationError as e:
        raise CaseFileError(f"{what}: {_where(e)}") from e


def load_case(path: str | Path) -> RunCase:
    """Decode a case file; its relative paths become relative to its folder. ``CaseFileError`` when bad."""
    p = Path(path)
    try:
        case = msgspec.toml.decode(p.read_bytes(), type=RunCase)
    except OSError as e:
        raise CaseFileError(f"case file {p}: {e.strerror or e}") from e
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        raise CaseFileError(f"case file {p}: {_where(e)}") from e
    for section, key in PATH_KEYS:
        holder = case if section is None else getattr(case, section)
        value = getattr(holder, key)
        if value is not None and not Path(value).is_absolute():
            case = _set(case, section, key, str(p.parent / value))
    return case


def _set(case: RunCase, section: str | None, key: str, value: object) -> RunCase:
    if section is None:
        return msgspec.structs.replace(case, **{key: value})
    return msgspec.structs.replace(case, **{section: msgspec.structs.replace(getattr(case, section), **{key: value})})


def absolute_paths(case: RunCase) -> RunCase:
    """``case`` with its relative paths (``PATH_KEYS``) made absolute from the working folder: a printed case saved
    to another folder names the same files.
    """
    for section, key in PATH_KEYS:
        value = getattr(case if section is None else getattr(case, section), key)
        if value is not None:
            case = _set(case, section, key, str(Path(value).absolute()))
    return case


def apply_flags(case: RunCase, args: argparse.Namespace) -> RunCase:
    """``case`` with every flag of :data:`RUN_FLAGS` given on the command line laid over it, checked."""
    for dest, (section, key, setting) in RUN_FLAGS.items():
        value = getattr(args, dest, None)
        if _given(value):
            case = _set(case, section, key, setting(value))
    return _check(case, "the command line")


def agent_options_from_args(args: argparse.Namespace) -> AgentOptions:
    """The default agent options with the agent flags that ``cvvc.cli_options`` adds, where given."""
    case = RunCase()
    for dest in AGENT_FLAGS:
        value = getattr(args, dest, None)
        if _given(value):
            section, key, setting = RUN_FLAGS[dest]
            case = _set(case, section, key, setting(value))
    return _check(case, "the command line").agent


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    return json.dumps(value)  # a TOML basic string: JSON's escapes are TOML's


def _lines(holder: msgspec.Struct, defaults: msgspec.Struct, skip: tuple[str, ...] = ()) -> list[str]:
    """One commented ``key = value`` per field of ``holder`` (not a section), with its description and default."""
    out = []
    for f in msgspec.structs.fields(holder):
        if f.name in skip:
            continue
        meta = getattr(f.type, "__metadata__", ())
        description = next((m.description for m in meta if getattr(m, "description", None)), "")
        value, default = getattr(holder, f.name), getattr(defaults, f.name)
        note = "" if value == default else f" [default: {'not set' if default is None else _toml_value(default)}]"
        out.append(f"# {description}{note}")
        out.append(f'# {f.name} = "..."' if value is None else f"{f.name} = {_toml_value(value)}")
    return out


def case_toml(case: RunCase | None = None, *, header: str = "") -> str:
    """``case`` (None: the defaults) as a commented TOML case file: every setting, its description, and its default
    where the value differs. Decoding the text gives ``case`` back (``load_case``).
    """
    case = case or RunCase()
    defaults = RunCase()
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    lines += ["# A cvvc case file (docs/case-file.md): `cvvc run case.toml` runs it; flags given on the command line",
              "# override it; a key left out takes its default; paths are relative to this file's folder.", ""]
    lines += _lines(case, defaults, skip=SECTIONS)
    for section in SECTIONS:
        holder = getattr(case, section)
        doc = (type(holder).__doc__ or "").strip().splitlines()[0]
        lines += ["", f"[{section}]  # {doc}", *_lines(holder, getattr(defaults, section))]
    return "\n".join(lines) + "\n"


def write_case(path: str | Path, *, force: bool = False) -> Path:
    """Write the defaults' case file to ``path`` (refuse an existing file unless ``force``)."""
    p = Path(path)
    if p.exists() and not force:
        raise CaseFileError(f"{p} exists; give another name or --force to overwrite it")
    try:
        p.write_text(case_toml())
    except OSError as e:
        raise CaseFileError(f"cannot write {p}: {e.strerror or e}") from e
    return p
