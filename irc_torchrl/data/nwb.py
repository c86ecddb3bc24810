"""The schema's table in Neurodata Without Borders files (needs ``pynwb``: ``irc-torchrl[nwb]``).

Behaviour lives in the processing module ``behavior``: the state's distance fields as the
:class:`~pynwb.behavior.SpatialSeries` ``position`` (in a ``Position``), its angles as
``SpatialSeries`` in a ``CompassDirection``, its other fields (velocities) and the actions as
:class:`~pynwb.TimeSeries` in ``BehavioralTimeSeries`` ``state`` and ``action``. All share one
vector of session timestamps. The trials table holds each trial's start and stop, its target
and its task θ (``theta.<name>`` columns). Trials follow one another with a one-second gap.
"""

from __future__ import annotations

import datetime
import re
import uuid
from pathlib import Path

import numpy as np
from pynwb import NWBHDF5IO, NWBFile, TimeSeries
from pynwb.behavior import BehavioralTimeSeries, CompassDirection, Position, SpatialSeries

from irc_torchrl.data.units import UNITS
from irc_torchrl.data.validate import THETA_PREFIX
from irc_torchrl.envs.model import TaskModel

__all__ = ["NEUTRAL_UNITS", "read_nwb", "unit_scale", "write_nwb"]

#: seconds between the end of one trial and the start of the next on the session clock
TRIAL_GAP = 1.0

Columns = dict[str, np.ndarray]
#: NWB units that name no scale: read in the task's own units
NEUTRAL_UNITS = {"", "si", "n.a.", "a.u.", "dimensionless", "unknown", "none"}
#: spellings of the units of :data:`~irc_torchrl.data.units.UNITS`, made their short forms
_SPELLINGS = [
    (r"\s*(per\s+second|/\s*s(ec(ond)?)?|[\s.]*s\^?-1|[\s.]*s⁻¹)$", "/s"),
    (r"^(centi)(meter|metre)s?", "cm"),
    (r"^(milli)(meter|metre)s?", "mm"),
    (r"^(meter|metre)s?", "m"),
    (r"^radians?", "rad"),
    (r"^(degrees?|°)", "deg"),
]


def _layout(model: TaskModel) -> tuple[list[str], list[str], list[str]]:
    """The state's position, angle and other fields."""
    units = dict(zip(model.state_names, model.state_units, strict=True))
    position = [n for n, u in units.items() if u == "distance"]
    angles = [n for n, u in units.items() if u == "rad"]
    return position, angles, [n for n in model.state_names if n not in position + angles]


def write_nwb(
    columns: Columns,
    path: Path,
    model: TaskModel,
    time_column: str = "time",
    trial_column: str = "trial",
) -> None:
    """Write the schema's table (one row per step) to the NWB file ``path``.

    Trial numbers must be integers: they become the trials table's ids, and ``0.1`` and
    ``0.2`` would both be written as trial 0, a file that cannot be read back.
    """
    trials = columns[trial_column]
    ids = np.asarray(trials, dtype=np.float64)
    bad = ~np.isfinite(ids) | (ids != np.round(ids))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"NWB: field {trial_column!r} is {ids[row]} at row {row + 1} (rows counted from 1); "
            "expected integer trial numbers (the ids of the NWB trials table)"
        )
    labels = list(dict.fromkeys(trials.tolist()))
    time = columns[time_column].astype(np.float64)
    session = np.empty_like(time)
    nwb = NWBFile(
        session_description="held trials written by irc-torchrl",
        identifier=str(uuid.uuid4()),
        session_start_time=datetime.datetime.now(datetime.UTC),
    )
    extra = [n for n in columns if n.startswith(THETA_PREFIX)]
    for name in [*model.target_names, *extra]:
        nwb.add_trial_column(name=name, description=f"{name} of the trial (one value per trial)")
    start = 0.0
    for label in labels:
        rows = trials == label
        session[rows] = start + time[rows] - time[rows][0]
        stop = float(session[rows][-1])
        values = {n: float(columns[n][rows][0]) for n in [*model.target_names, *extra]}
        nwb.add_trial(start_time=start, stop_time=stop, id=int(label), **values)
        start = stop + TRIAL_GAP
    position, angles, others = _layout(model)
    units = dict(zip(model.state_names, model.state_units, strict=True))
    behavior = nwb.create_processing_module("behavior", "the agent's state and actions")
    pos = SpatialSeries(
        name="position",
        data=np.stack([columns[n] for n in position], -1),
        timestamps=session,
        reference_frame="the task's origin; columns " + ", ".join(position),
        unit="metres",
    )
    behavior.add(Position(spatial_series=pos, name="Position"))
    if angles:
        behavior.add(
            CompassDirection(
                name="CompassDirection",
                spatial_series=[
                    SpatialSeries(
                        name=n,
                        data=columns[n],
                        timestamps=pos,
                        reference_frame="x axis",
                        unit="radians",
                    )
                    for n in angles
                ],
            )
        )
    if others:
        series = [
            TimeSeries(name=n, data=columns[n], timestamps=pos, unit=units[n]) for n in others
        ]
        behavior.add(BehavioralTimeSeries(name="state", time_series=series))
    actions = [
        TimeSeries(name=n, data=columns[n], timestamps=pos, unit="dimensionless")
        for n in model.action_names
    ]
    behavior.add(BehavioralTimeSeries(name="action", time_series=actions))
    with NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)


def read_nwb(
    path: Path, model: TaskModel, time_column: str = "time", trial_column: str = "trial"
) -> Columns:
    """The schema's table from an NWB file laid out as :func:`write_nwb` writes it."""
    try:
        io = NWBHDF5IO(str(path), "r")
        nwb = io.read()
    except Exception as err:  # h5py and hdmf raise many types for a file that is not NWB
        raise ValueError(f"{path}: not an NWB file ({err}); expected one written by pynwb") from err
    with io:
        try:
            behavior = nwb.processing["behavior"]
            pos = behavior["Position"]["position"]
        except KeyError as err:
            raise KeyError(
                f"{path}: missing {err}; expected processing module 'behavior' with a "
                "Position 'position' SpatialSeries (see docs/trajectory_schema.md)"
            ) from None
        stamps = np.asarray(pos.get_timestamps(), dtype=np.float64)  # or starting time and rate
        data = _values(pos, "distance", path).reshape(len(stamps), -1)
        position, angles, others = _layout(model)
        table: Columns = {n: data[:, i] for i, n in enumerate(position)}
        kinds = dict(zip(model.state_names, model.state_units, strict=True))
        containers = {
            **{n: "CompassDirection" for n in angles},
            **{n: "state" for n in others},
            **{n: "action" for n in model.action_names},
        }
        for name, container in containers.items():
            try:
                series = behavior[container][name]
            except KeyError:
                raise KeyError(
                    f"{path}: missing the series {name!r}; expected it in {container!r} of "
                    "processing module 'behavior' (see docs/trajectory_schema.md)"
                ) from None
            table[name] = _values(series, kinds.get(name), path)
            clock = np.asarray(series.get_timestamps(), dtype=np.float64)
            same = len(table[name]) == len(clock) == len(stamps)
            if not (same and np.allclose(clock, stamps, rtol=0, atol=1e-9)):
                raise ValueError(
                    f"{path}: series {name!r} has {len(table[name])} values at {len(clock)} "
                    f"times, not at the {len(stamps)} of 'position' (from {stamps[0]:.6g} s); "
                    "expected every series on one clock"
                )
        if nwb.trials is None:
            raise KeyError(f"{path}: missing the trials table; expected one row per trial")
        trials = nwb.trials.to_dataframe()
        trial = np.full(len(stamps), np.nan)
        time = np.full(len(stamps), np.nan)
        # the schema's (a lab's other columns, text among them, are its own business)
        names = [n for n in trials.columns if n in model.target_names or n.startswith(THETA_PREFIX)]
        per_trial = {n: np.full(len(stamps), np.nan) for n in names}
        # a trial's bounds hold the samples on them, whatever their floating-point rounding
        slack = 1e-3 * float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
        for label, row in trials.iterrows():
            rows = (stamps >= row["start_time"] - slack) & (stamps <= row["stop_time"] + slack)
            trial[rows] = label
            time[rows] = stamps[rows] - row["start_time"]
            for name, values in per_trial.items():
                try:
                    values[rows] = float(row[name])
                except (TypeError, ValueError):
                    raise ValueError(
                        f"{path}: trials table, trial {label}, column {name!r}: {row[name]!r}; "
                        "expected a number"
                    ) from None
    # a rig records between trials too: only the trials table's trials are the task's
    inside = np.isfinite(trial)
    columns = {trial_column: trial, time_column: time, **table, **per_trial}
    return {name: np.asarray(values)[inside] for name, values in columns.items()}


def _values(series: TimeSeries, kind: str | None, path: Path) -> np.ndarray:
    """A series' data in the task's units (``kind``: the field's, ``None`` for a control):
    NWB stores ``data × conversion + offset`` in the series' ``unit``, converted here."""
    offset = getattr(series, "offset", 0.0) or 0.0
    value = np.asarray(series.data[:], dtype=np.float64) * series.conversion + offset
    if kind is None:  # a control: dimensionless
        return value
    return value * unit_scale(series.unit, kind, f"{path}: series {series.name!r}")


def unit_scale(unit: str, kind: str, where: str) -> float:
    """The factor from an NWB ``unit`` to the task's unit ``kind`` (``"distance"``, ``"rad/s"``,
    ...): a unit of :data:`~irc_torchrl.data.units.UNITS` however spelled (``"centimeters"``,
    ``"cm s^-1"``, ``"°"``), or 1 for the task's own or none named (``"SI"``); any other
    unit is refused rather than read as the task's."""
    spelled = str(unit).strip().lower()
    if spelled in NEUTRAL_UNITS or spelled == kind:
        return 1.0
    for pattern, short in _SPELLINGS:
        spelled = re.sub(pattern, short, spelled)
    table = UNITS.get(kind, {})  # a task of the user's may have kinds of its own
    if spelled not in table:
        known = f"one of {', '.join(table)} (any spelling), or " if table else ""
        raise ValueError(
            f"{where}: unit {unit!r}; expected a {kind} unit: {known}{kind!r} or 'SI' for the "
            "task's own"
        )
    return table[spelled]
