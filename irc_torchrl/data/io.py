"""Recorded trials in and out: NPZ, CSV, NWB and TensorDict memory-mapped folders.

Every format holds the same table (docs/trajectory_schema.md): one row per time step with a
trial column, the time in seconds, the model's state, action and target columns, and optional
``theta.<name>`` columns for the task's θ. :func:`read_trials` checks the table
(:mod:`irc_torchrl.data.validate`), converts units, resamples each trial to the model's time
step and returns held trials ``[n_trials, T]`` ready for a fit. :func:`write_trials` writes
held trials back; every write goes to a temporary file or folder renamed when complete.
"""

from __future__ import annotations

import csv
import gzip
import importlib
import io
import json
import math
import warnings
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical

from irc_torchrl.data.files import atomic_dir, atomic_path, check_space
from irc_torchrl.data.trajectories import TRIAL_KEYS, validate_trials
from irc_torchrl.data.units import convert_units, unwrap_angles
from irc_torchrl.data.validate import (
    THETA_PREFIX,
    Trial,
    check_columns,
    check_kinematics,
    check_stops,
    check_targets,
    check_trial,
    required_columns,
    split_trials,
)
from irc_torchrl.envs.model import TaskModel, check_action_spec

__all__ = [
    "SUFFIXES",
    "load_memmap",
    "nwb_module",
    "read_trials",
    "recording_suffix",
    "write_trials",
    "trials_to_columns",
]

#: the file formats a recording may have (else a TensorDict memmap folder)
SUFFIXES = (".npz", ".csv", ".csv.gz", ".nwb")

#: the median time step may differ from the model's by this fraction before resampling
RESAMPLE_TOLERANCE = 0.01
#: a step this many times the median is a gap (missing samples), not one model step
GAP = 1.5

Columns = dict[str, np.ndarray]


# --- public API ------------------------------------------------------------------------------
def read_trials(
    path: str | Path,
    model: TaskModel,
    *,
    time_column: str = "time",
    trial_column: str = "trial",
    units: Mapping[str, str] | None = None,
    resample: bool = True,
) -> TensorDict:
    """Read a recording into held trials ``[n_trials, T]``, refusing anything malformed.

    Args:
        path: ``.npz``, ``.csv``, ``.csv.gz``, ``.nwb`` (needs ``pynwb``), or a TensorDict
            memmap folder.
        model: the task; its names and units define the columns (see the schema).
        time_column, trial_column: the names of the time (s) and trial columns.
        units: ``{column: unit}`` where the recording differs from the model's units,
            e.g. ``{"x": "cm", "heading": "deg"}``. Angles wrapped into ``[-π, π]`` are
            unwrapped (:func:`~irc_torchrl.data.units.unwrap_angles`).
        resample: put each trial on the model's time grid when the recording's median step
            differs from ``model.dt`` by more than 1% (a warning says so; gaps in a trial are
            then interpolated across). Otherwise each sample is read as one model step, and a
            trial with a gap (a step over 1.5 times the median) is refused.
        Columns outside the schema (its required ones and ``theta.<name>``) are not read.

    Returns:
        ``state``, ``action``, ``target``, ``mask``, ``task_theta`` (θ columns, else the θ
        space's default), ``time`` (seconds since the trial's first sample) and ``trial``
        (the recording's trial number), padded to the longest trial by repeating its last step.
    """
    check_action_spec(model)
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise FileNotFoundError(f"{source}: no such file or folder")
    reader = _reader(path)
    of_series = sorted(set(units or {}) - set(model.target_names))
    if of_series and reader is _read_nwb:
        raise ValueError(
            f"{source}: units: an NWB series carries its own unit (its unit and conversion), "
            f"read as such; expected units= for the trials table's targets alone "
            f"({', '.join(model.target_names)}) in an NWB file, got {dict(units)}"
        )
    columns = reader(path, model, time_column, trial_column)
    check_columns(columns, model, source, time_column, trial_column)
    # the schema's other columns (eye position, events, ...) are the user's business
    used = _used_columns(model, time_column, trial_column)
    columns = {name: value for name, value in columns.items() if used(name)}
    columns = convert_units(columns, units or {}, model, source, time_column)
    trials = [
        (label, unwrap_angles(trial, model))
        for label, trial in split_trials(columns, source, trial_column)
    ]
    for label, trial in trials:
        check_trial(label, trial, model, source, time_column)
    # an NWB file's times are seconds by definition: no unit of its own to declare
    seconds = reader is _read_nwb
    trials = _on_model_grid(trials, model, source, time_column, trial_column, resample, seconds)
    with torch.device("cpu"):  # read onto the CPU whatever torch's default device
        held = _pack(trials, model, time_column, trial_column)
    check_stops(held, model, source)  # before validate_trials: by the file and trial number
    validate_trials(held, model)
    check_kinematics(held, model, source)
    check_targets(held, model, source)
    return held


def write_trials(trials: TensorDictBase, path: str | Path, model: TaskModel) -> Path:
    """Write one agent's held trials (``[n_trials, T]``, or ``[1, n_trials, T]``) to ``path``.

    The format follows the suffix (``.npz``, ``.csv``, ``.csv.gz``: gzip-compressed, ``.nwb``);
    a path without a suffix is a TensorDict memmap folder. Only the recorded steps (``mask``)
    are written to the tables; the folder keeps the padded layout. A recording is one agent's,
    as :func:`read_trials` and ``irc fit`` read it: several agents are refused, not pooled.
    """
    path = Path(path)
    _one_agent(trials, "trials")
    trials = validate_trials(trials, model).reshape(-1, trials.shape[-1])
    if path.suffix == "":
        held = trials.select(*TRIAL_KEYS).clone()
        held["time"] = _field(trials, "time", model)
        held["trial"] = _field(trials, "trial", model)
        path.parent.mkdir(parents=True, exist_ok=True)
        size = sum(t.nbytes for t in held.values(include_nested=True, leaves_only=True))
        check_space(path.parent, size, f"the memmap recording {path.name}")
        with atomic_dir(path) as tmp:
            held.memmap(tmp)
        return path
    writer = _writer(path)
    columns = trials_to_columns(trials, model)
    with atomic_path(path, extension=recording_suffix(path)) as tmp:
        writer(columns, tmp, model)
    return path


def _one_agent(trials: TensorDictBase, field: str) -> None:
    """Refuse held trials of several agents ``[n_agents, n_trials, T]``: a recording is one's."""
    if trials.ndim == 3 and trials.shape[0] != 1:
        raise ValueError(
            f"{field}: holds the trials of {trials.shape[0]} agents ([agent, trial, step]); a "
            "recording is one agent's: write each with write_trials(trials[i], ...)"
        )


def trials_to_columns(
    trials: TensorDictBase, model: TaskModel, time_column: str = "time", trial_column: str = "trial"
) -> Columns:
    """The recorded steps of held trials ``[n, T]`` as the schema's table, one row per step."""
    trials = trials.detach().cpu()
    mask = trials["mask"].numpy().astype(bool)
    columns = {
        trial_column: _field(trials, "trial", model).numpy()[mask],
        time_column: _field(trials, "time", model).numpy()[mask],
    }
    state = trials["state"].numpy()
    columns.update({name: state[..., i][mask] for i, name in enumerate(model.state_names)})
    action = trials["action"].numpy()
    if isinstance(model.action_spec, Categorical):
        columns[model.action_names[0]] = action[mask].astype(np.int64)
    else:
        columns.update({name: action[..., i][mask] for i, name in enumerate(model.action_names)})
    target = trials["target"].numpy()
    columns.update({name: target[..., i][mask] for i, name in enumerate(model.target_names)})
    theta = trials["task_theta"].numpy()
    for i, name in enumerate(model.theta_space.names):
        columns[THETA_PREFIX + name] = theta[..., i][mask]
    return columns


# --- formats ---------------------------------------------------------------------------------
Reader = Callable[[Path, TaskModel, str, str], Columns]
Writer = Callable[[Columns, Path, TaskModel], None]


def _reader(path: Path) -> Reader:
    if path.is_dir():
        memmap = (path / "meta.json").is_file()
        inside = [] if memmap else sorted(f for f in path.iterdir() if _suffixed(f))
        if inside:  # a session's folder of recordings
            names = ", ".join(f.name for f in inside[:3]) + (", ..." if len(inside) > 3 else "")
            raise ValueError(
                f"{path}: a folder of recordings ({names}), not a TensorDict memmap folder; "
                f"expected one recording per path: give the files (e.g. "
                f"{path}/*{recording_suffix(inside[0])})"
            )
        return _read_memmap
    readers = dict(zip(SUFFIXES, (_read_npz, _read_csv, _read_csv, _read_nwb), strict=True))
    if not _suffixed(path):
        raise ValueError(
            f"{path}: unknown format {path.suffix!r}; expected {', '.join(SUFFIXES)} "
            "or a TensorDict memmap folder"
        )
    return readers[recording_suffix(path)]


def _writer(path: Path) -> Writer:
    writers = dict(zip(SUFFIXES, (_write_npz, _write_csv, _write_csv, _write_nwb), strict=True))
    if not _suffixed(path):
        raise ValueError(
            f"{path}: unknown format {path.suffix!r}; expected {', '.join(SUFFIXES)} "
            "or no suffix for a TensorDict memmap folder"
        )
    return writers[recording_suffix(path)]


def recording_suffix(path: str | Path) -> str:
    """A recording's format suffix: ``.csv.gz`` for a gzip-compressed CSV, else the path's
    last suffix (``""`` for a memmap folder)."""
    path = Path(path)
    return ".csv.gz" if path.name.endswith(".csv.gz") else path.suffix


def _suffixed(path: Path) -> bool:
    """Whether ``path`` ends in the suffix of a recording's file format."""
    return recording_suffix(path) in SUFFIXES


def _used_columns(model: TaskModel, time_column: str, trial_column: str) -> Callable[[str], bool]:
    """Whether a column is read: the schema's required ones and ``theta.<name>``; readers
    leave the others unread (an empty placeholder keeps their name for misspelling hints)."""
    required = set(required_columns(model, time_column, trial_column))
    return lambda name: name in required or name.startswith(THETA_PREFIX)


def _read_npz(path: Path, model: TaskModel, time_column: str, trial_column: str) -> Columns:
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: not an NPZ archive; expected a file written by np.savez")
    used = _used_columns(model, time_column, trial_column)
    columns = {}
    try:
        with np.load(path, allow_pickle=False) as archive:
            for name in archive.files:
                if not used(name):
                    columns[name] = np.empty(0)
                    continue
                try:
                    columns[name] = archive[name]
                except ValueError:  # an object array, refused without unpickling
                    raise ValueError(
                        f"{path}: column {name!r} holds Python objects; expected numeric "
                        "arrays, one per column (object arrays are never unpickled)"
                    ) from None
    except (zipfile.BadZipFile, EOFError, OSError) as err:
        raise ValueError(f"{path}: a damaged NPZ archive ({err}); write it again") from None
    return columns


def _write_npz(columns: Columns, tmp: Path, model: TaskModel) -> None:
    with open(tmp, "wb") as f:
        np.savez(f, **columns)


def _read_csv(path: Path, model: TaskModel, time_column: str, trial_column: str) -> Columns:
    try:
        opened = gzip.open if recording_suffix(path) == ".csv.gz" else open
        with opened(path, "rt", newline="", encoding="utf-8-sig") as f:  # -sig: Excel's BOM
            reader = csv.reader(f)  # with each row's line in the file, blank lines skipped
            read = [(reader.line_num, row) for row in reader if row]
    except (UnicodeDecodeError, csv.Error) as err:
        raise ValueError(
            f"{path}: not a CSV text file ({err}); expected comma-separated values"
        ) from err
    except (gzip.BadGzipFile, EOFError, zlib.error) as err:
        raise ValueError(f"{path}: a damaged gzip file ({err}); write it again") from None
    if not read:
        return {}
    lines, rows = zip(*read, strict=True)
    header = [name.strip() for name in rows[0]]
    if len(header) == 1 and any(mark in header[0] for mark in ";\t|"):
        raise ValueError(
            f"{path}: the header {header[0][:60]!r} is one column; expected comma-separated "
            "values (export with commas, not semicolons or tabs)"
        )
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated:
        raise ValueError(
            f"{path}: column(s) {repeated} appear more than once in the header; expected "
            "each column once"
        )
    used = _used_columns(model, time_column, trial_column)
    values = np.full((len(rows) - 1, len(header)), np.nan)
    for r, (line, row) in enumerate(zip(lines[1:], rows[1:], strict=True)):
        if len(row) != len(header):
            raise ValueError(
                f"{path}: line {line} has {len(row)} values; expected {len(header)}, one per "
                f"column of the header {header}"
            )
        for c, cell in enumerate(row):
            if not used(header[c]):
                continue
            try:
                values[r, c] = float(cell) if cell.strip() else np.nan
            except ValueError:
                raise ValueError(
                    f"{path}: line {line}, column {header[c]!r}: {cell!r} is not a number; "
                    "expected numbers (empty or NaN for a gap)"
                ) from None
    return {name: values[:, c] if used(name) else np.empty(0) for c, name in enumerate(header)}


def _write_csv(columns: Columns, tmp: Path, model: TaskModel) -> None:
    names = list(columns)
    # integers as they are, float64 (trial numbers like 20240501.001) by the shortest text that
    # reads back the same, float32 by the 9 digits that do
    cells = [
        [str(v) for v in col.tolist()]
        if np.issubdtype(col.dtype, np.integer)
        else [repr(v) for v in col.tolist()]
        if col.dtype == np.float64
        else [f"{v:.9g}" for v in col.tolist()]
        for col in columns.values()
    ]
    text = io.StringIO(newline="")
    writer = csv.writer(text, lineterminator="\n")  # csv's default is "\r\n", even here
    writer.writerow(names)
    writer.writerows(zip(*cells, strict=True))
    data = text.getvalue().encode()
    # compressed without a time stamp or a name: the same trials give the same bytes
    gzipped = recording_suffix(tmp) == ".csv.gz"  # a temporary keeps the extension
    tmp.write_bytes(gzip.compress(data, mtime=0) if gzipped else data)


def load_memmap(path: str | Path) -> TensorDict:
    """A TensorDict memmap folder (``write_trials``'s, ``irc recover``'s ``trials/``), opened
    once its files are checked against ``meta.json``; a damaged folder is a ValueError. Only
    what is indexed is read."""
    path = Path(path)
    _check_memmap_sizes(path)
    try:
        return TensorDict.load_memmap(path)
    except (FileNotFoundError, KeyError, ValueError, RuntimeError) as err:
        raise ValueError(
            f"{path}: not a TensorDict memmap folder ({err}); expected one written by "
            "write_trials or TensorDict.memmap"
        ) from None


def _read_memmap(path: Path, model: TaskModel, time_column: str, trial_column: str) -> Columns:
    trials = load_memmap(path)
    missing = [k for k in TRIAL_KEYS if k not in trials.keys()]
    if missing:
        raise KeyError(f"{path}: missing field(s) {missing}; held trials need {list(TRIAL_KEYS)}")
    try:  # shapes and masks before the table is cut from them
        trials = validate_trials(trials, model)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: {err}") from None
    _one_agent(trials, str(path))  # e.g. irc recover's trials/: pooled, they'd read as one agent
    return trials_to_columns(trials.reshape(-1, trials.shape[-1]), model, time_column, trial_column)


def _check_memmap_sizes(path: Path) -> None:
    """Refuse a memmap folder whose files are not the size ``meta.json`` gives them: a
    truncated file would read as zeros (and be grown back on opening)."""
    try:
        meta = json.loads((path / "meta.json").read_text())
    except (OSError, ValueError):
        return  # TensorDict.load_memmap says what is wrong with it
    for key, leaf in meta.items() if isinstance(meta, dict) else ():
        if isinstance(leaf, dict) and "type" in leaf and (path / key).is_dir():  # nested
            _check_memmap_sizes(path / key)
            continue
        file = path / f"{key}.memmap"
        if not (isinstance(leaf, dict) and file.is_file()):
            continue
        dtype = getattr(torch, str(leaf.get("dtype", "")).removeprefix("torch."), None)
        if not isinstance(dtype, torch.dtype) or not isinstance(leaf.get("shape"), list):
            continue
        expected, size = math.prod(leaf["shape"]) * dtype.itemsize, file.stat().st_size
        if size != expected:
            raise ValueError(
                f"{file}: {size} bytes; expected {expected} ({key} of shape "
                f"{leaf['shape']}, {dtype}, per meta.json): truncated or overwritten"
            )


def nwb_module() -> ModuleType:
    """The NWB reader/writer, or an ImportError that says how to install pynwb."""
    try:
        nwb = importlib.import_module("irc_torchrl.data.nwb")
    except ImportError as err:
        raise ImportError(
            f"NWB files need pynwb ({err}); install it with: pip install 'irc-torchrl[nwb]'"
        ) from err
    return nwb


def _read_nwb(path: Path, model: TaskModel, time_column: str, trial_column: str) -> Columns:
    return nwb_module().read_nwb(path, model, time_column, trial_column)


def _write_nwb(columns: Columns, tmp: Path, model: TaskModel) -> None:
    nwb_module().write_nwb(columns, tmp, model)


# --- from table to held trials ---------------------------------------------------------------
def _field(trials: TensorDictBase, key: str, model: TaskModel) -> torch.Tensor:
    """``time`` (seconds) or ``trial`` (number) of held trials, made up when absent."""
    if key in trials.keys():
        return trials[key]
    n, steps = trials.shape
    if key == "time":  # rounded: 3 × 0.1 is written 0.3, not 0.30000000000000004
        time = torch.arange(steps, dtype=torch.float64, device=trials.device) * model.dt
        return time.round(decimals=12).expand(n, steps)
    return torch.arange(n, device=trials.device).unsqueeze(-1).expand(n, steps)


def _on_model_grid(
    trials: list[tuple[int | float, Trial]],
    model: TaskModel,
    source: str,
    time_column: str,
    trial_column: str,
    resample: bool,
    seconds: bool = False,
) -> list[tuple[int | float, Trial]]:
    """Each trial with its time from its start, resampled to ``model.dt`` where it differs
    (``seconds``: the format's times are seconds, with no unit to declare)."""
    steps = np.concatenate([np.diff(t[time_column]) for _, t in trials])
    # trials of one sample each (an agent stopping at once) say nothing of the step
    step = float(np.median(steps)) if steps.size else model.dt
    on_grid = abs(step - model.dt) <= RESAMPLE_TOLERANCE * model.dt
    resample = resample and not on_grid
    # a clock in ms read as s steps slower than the task's: the step is 1000× too long
    slow = not seconds and step > (1 + RESAMPLE_TOLERANCE) * model.dt
    for label, trial in trials:  # before any resampling: a time in ms made each 1000× longer
        time = trial[time_column].astype(np.float64)
        n = _grid_steps(time[-1] - time[0], model.dt) if resample else len(time)
        if n > model.max_steps:
            _refuse_long(source, label, time_column, n, time[-1] - time[0], model, slow)
    if not on_grid and not resample:
        warnings.warn(
            f"{source}: the median time step is {step:.6g} s but the model steps {model.dt} s; "
            "kept as recorded (resample=False)",
            stacklevel=3,
        )
    if resample:
        warnings.warn(
            f"{source}: resampled every trial from a median time step of {step:.6g} s "
            f"to the model's {model.dt} s (linear; discrete actions the previous sample; each "
            "trial's last step its last recorded action)",
            stacklevel=3,
        )
    discrete = {trial_column}
    if isinstance(model.action_spec, Categorical):
        discrete.add(model.action_names[0])
    out = []
    longest = (0.0, None, 0.0, 0)  # the longest gap resampling fills: s, trial, from, steps
    for label, trial in trials:
        recorded = trial[time_column].astype(np.float64)
        time = recorded - recorded[0]
        gaps = np.flatnonzero(np.diff(time) > GAP * step)
        if gaps.size and not resample:
            i = int(gaps[0])
            raise ValueError(
                f"{source}: trial {label}, field {time_column!r}: time jumps from "
                f"{recorded[i]:.6g} s to {recorded[i + 1]:.6g} s at sample {i + 1}, more than "
                f"{GAP:g} steps of {step:.6g} s; expected evenly spaced samples, each read as "
                "one model step (fill or cut the gap)"
            )
        if resample:
            grid = model.dt * np.arange(_grid_steps(time[-1], model.dt))
            previous = np.searchsorted(time, grid + 1e-9 * model.dt, side="right") - 1
            for i in gaps:  # the longest gap holding model steps no sample was near
                inside = int(((grid > time[i] + step) & (grid < time[i + 1] - step)).sum())
                if inside and time[i + 1] - time[i] > longest[0]:
                    longest = (float(time[i + 1] - time[i]), label, float(recorded[i]), inside)
            resampled = {
                name: values[previous] if name in discrete else np.interp(grid, time, values)
                for name, values in trial.items()
            }
            for name in model.action_names:  # a stop between the last two steps: the last's
                resampled[name][-1] = trial[name][-1]
            trial, time = resampled, grid
        out.append((label, {**trial, time_column: time}))
    seconds, label, start, inside = longest
    if inside:
        warnings.warn(
            f"{source}: trial {label}: a gap of {seconds:.6g} s from {start:.6g} s was "
            f"interpolated across ({inside} model step{'s' * (inside > 1)}, actions included, "
            "made up; the longest such gap of the recording): cut the trial there if the agent "
            "was not tracked",
            stacklevel=3,
        )
    return out


def _grid_steps(duration: float, dt: float) -> int:
    """How many steps of ``dt`` a trial of ``duration`` seconds takes on the model's grid."""
    return int(np.floor(duration / dt + 1e-6)) + 1


def _refuse_long(
    source: str,
    label: int | float,
    time_column: str,
    n: int,
    duration: float,
    model: TaskModel,
    slow: bool,
) -> None:
    """Refuse a trial of ``n`` model steps, over the task's ``max_steps``; where the recording
    steps slower than the task (``slow``) and the trial would be one of the task's were its
    time in ms (1000× too long: at least a step, at most ``max_steps``), say so."""
    longest = (model.max_steps - 1) * model.dt
    in_ms = slow and 1000 * model.dt <= duration <= 1000 * longest
    hint = f" (it lasts {duration:.6g} s: a time in ms? declare units.{time_column}=ms)"
    raise ValueError(
        f"{source}: trial {label}, field {time_column!r}: {n} samples, each read as a model "
        f"step; the task ends every trial within max_steps={model.max_steps} steps of "
        f"{model.dt:g} s, so cut or drop longer trials{hint if in_ms else ''}"
    )


def _pack(
    trials: list[tuple[int | float, Trial]], model: TaskModel, time_column: str, trial_column: str
) -> TensorDict:
    """The held-trial layout, each trial padded to the longest by repeating its last step."""
    steps = max(len(t[time_column]) for _, t in trials)

    def stack(names: tuple[str, ...] | list[str], dtype: torch.dtype) -> torch.Tensor:
        rows = [
            np.stack([np.pad(t[n], (0, steps - len(t[n])), mode="edge") for n in names], -1)
            for _, t in trials
        ]
        return torch.as_tensor(np.stack(rows), dtype=dtype)

    theta_names = [THETA_PREFIX + n for n in model.theta_space.names]
    default = model.theta_space.default(torch.float64).numpy()
    for _, trial in trials:
        for name, value in zip(theta_names, default, strict=True):
            trial.setdefault(name, np.full(len(trial[time_column]), value))
    lengths = torch.tensor([len(t[time_column]) for _, t in trials])
    spec = model.action_spec
    if isinstance(spec, Categorical):
        action = stack(model.action_names, torch.int64)[..., 0]
    else:  # values past a bound by the checks' slack are an export's round-off
        low, high = (x.to("cpu") for x in (spec.space.low, spec.space.high))  # a GPU model's
        action = stack(model.action_names, torch.float32).clamp(low, high)
    labels = [label for label, _ in trials]
    # a label like 20240501.001 (session.trial) needs float64 to stay itself
    numbers = torch.tensor(
        labels, dtype=torch.float64 if any(isinstance(n, float) for n in labels) else torch.int64
    )
    return TensorDict(
        {
            "state": stack(model.state_names, torch.float32),
            "action": action,
            "target": stack(model.target_names, torch.float32),
            "mask": torch.arange(steps) < lengths.unsqueeze(-1),
            "task_theta": stack(theta_names, torch.float32),
            "time": stack([time_column], torch.float32)[..., 0],
            "trial": numbers.unsqueeze(-1).expand(-1, steps),
        },
        batch_size=[len(trials), steps],
    )
