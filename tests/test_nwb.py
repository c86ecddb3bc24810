"""NWB files (needs pynwb): trial numbers the trials table cannot hold are refused."""

from __future__ import annotations

import math

import pytest
import torch

from irc_torchrl.algorithms.simulate import simulate_agents
from irc_torchrl.data.io import read_trials, write_trials
from irc_torchrl.envs import Firefly2DModel

pytest.importorskip("pynwb")


def _numbered(model: Firefly2DModel, numbers: list[float]):
    """Random-action trials with at least two recorded steps, numbered ``numbers``."""
    theta = model.theta_space.default().unsqueeze(0)
    trials = simulate_agents(model, None, theta, 8, seed=0)[0]
    trials = trials[trials["mask"].sum(-1) >= 2][: len(numbers)]
    trials["trial"] = torch.tensor(numbers, dtype=torch.float64)[:, None].expand(trials.shape)
    return trials


def test_non_integer_trial_numbers_are_refused_before_writing(tmp_path):
    """0.1, 0.2 and 0.3 would all be written as trial 0: a file that cannot be read back."""
    model = Firefly2DModel()
    message = r"NWB: field 'trial' is 0.1 at row 1 \(rows counted from 1\); expected integer"
    with pytest.raises(ValueError, match=message):
        write_trials(_numbered(model, [0.1, 0.2, 0.3]), tmp_path / "t.nwb", model)
    assert list(tmp_path.iterdir()) == []
    write_trials(_numbered(model, [3.0, 5.0, 7.0]), tmp_path / "t.nwb", model)
    back = read_trials(tmp_path / "t.nwb", model)
    assert back["trial"][:, 0].tolist() == [3, 5, 7]


def _lab_nwb(
    path,
    columns,
    centimetres=False,
    between_trials=False,
    without=(),
    short=(),
    offset=0.0,
    cm_unit=False,
    rate=False,
    late=(),
    targets_cm=False,
):
    """An NWB file laid out as the schema says, written the way a lab's rig might: positions
    in cm declared by NWB's own ``conversion`` (from an origin ``offset`` m away) or by their
    ``unit`` (``cm_unit``), samples through the gaps between trials, a series not exported,
    one a sample short on its own clock or as long but half a sample late (``late``), or every
    series sampled at a rate (its starting time and rate, no timestamps) with an outcome in
    words in the trials table; its targets in cm (``targets_cm``: the table has no unit)."""
    import datetime
    import uuid

    import numpy as np
    from pynwb import NWBHDF5IO, NWBFile, TimeSeries
    from pynwb.behavior import BehavioralTimeSeries, CompassDirection, Position, SpatialSeries

    nwb = NWBFile("lab", str(uuid.uuid4()), datetime.datetime.now(datetime.UTC))
    for name in ("target_x", "target_y"):
        nwb.add_trial_column(name=name, description=name)
    if rate:
        nwb.add_trial_column(name="outcome", description="rewarded or missed")
    trial, stamps, start = columns["trial"], np.empty(len(columns["trial"])), 10.0
    for label in dict.fromkeys(trial.tolist()):
        rows = trial == label
        stamps[rows] = start + columns["time"][rows]
        per_trial = {
            n: float(columns[n][rows][0]) * (100.0 if targets_cm else 1.0)
            for n in ("target_x", "target_y")
        }
        if rate:
            per_trial["outcome"] = "missed"
        stop = float(stamps[rows][-1])
        nwb.add_trial(start_time=start, stop_time=stop, id=int(label), **per_trial)
        start = stop + (model_dt(columns) if rate else 2.0)  # at a rate: no gap in the clock
    data = {n: columns[n].astype(np.float64) for n in ("x", "y", "heading", "v", "w", "a_v", "a_w")}
    if between_trials:  # the rig keeps sampling, the agent parked, between trials
        gaps = np.arange(stamps[0], stamps[-1], 0.05)
        gaps = gaps[np.abs(gaps[:, None] - stamps[None]).min(1) > 0.5]
        parked = {n: np.full(len(gaps), 0.3) for n in data}
        order = np.argsort(np.concatenate([stamps, gaps]))
        stamps = np.concatenate([stamps, gaps])[order]
        data = {n: np.concatenate([data[n], parked[n]])[order] for n in data}
    scale = 100.0 if centimetres or cm_unit else 1.0
    clock = {"starting_time": float(stamps[0]), "rate": 1 / model_dt(columns)} if rate else {}
    behavior = nwb.create_processing_module("behavior", "behaviour")
    position = SpatialSeries(
        name="position", data=(np.stack([data["x"], data["y"]], -1) - offset) * scale,
        timestamps=None if rate else stamps, reference_frame="arena",
        unit="centimeters" if cm_unit else "metres", conversion=1.0 if cm_unit else 1 / scale,
        offset=offset, **clock,
    )  # fmt: skip
    behavior.add(Position(spatial_series=position, name="Position"))
    on_clock = clock or {"timestamps": position}
    heading = SpatialSeries(
        name="heading", data=data["heading"], reference_frame="x", unit="radians", **on_clock
    )
    behavior.add(CompassDirection(name="CompassDirection", spatial_series=[heading]))
    for container, names in (("state", ("v", "w")), ("action", ("a_v", "a_w"))):
        series = [
            TimeSeries(name=n, data=data[n][:-1], timestamps=stamps[:-1], unit="SI")
            if n in short
            else TimeSeries(name=n, data=data[n], timestamps=stamps + 0.05, unit="SI")
            if n in late
            else TimeSeries(name=n, data=data[n], unit="SI", **on_clock)
            for n in names
            if n not in without
        ]
        behavior.add(BehavioralTimeSeries(name=container, time_series=series))
    with NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)


def model_dt(columns) -> float:
    """The recording's sampling step (the task's: 0.1 s)."""
    return float(columns["time"][1] - columns["time"][0])


def test_a_rigs_nwb_file_is_read_as_nwb_means_it(tmp_path):
    """NWB's ``conversion`` was ignored (a cm file refused as a unit mistake), samples between
    the trials table's trials refused the file, and a missing series was called a NaN gap."""
    from irc_torchrl.data.io import trials_to_columns

    model = Firefly2DModel()
    trials = _numbered(model, [3.0, 5.0, 7.0])
    columns = trials_to_columns(trials, model)
    plain = tmp_path / "plain.nwb"
    _lab_nwb(plain, columns)
    expected = read_trials(plain, model)
    for name, options in {
        "cm.nwb": {"centimetres": True},
        "rig.nwb": {"between_trials": True},
        # each failed: 'NoneType' object is not subscriptable; could not convert 'missed';
        # and the unit read as metres (a file 100× too large)
        "rate.nwb": {"rate": True},
        "cm_unit.nwb": {"cm_unit": True},
    }.items():
        _lab_nwb(tmp_path / name, columns, **options)
        back = read_trials(tmp_path / name, model)
        assert back["trial"][:, 0].tolist() == [3, 5, 7]
        torch.testing.assert_close(back["state"], expected["state"])
        assert torch.equal(back["mask"], expected["mask"])
    _lab_nwb(tmp_path / "no_v.nwb", columns, without=("v",))
    with pytest.raises(KeyError, match="missing the series 'v'; expected it in 'state'"):
        read_trials(tmp_path / "no_v.nwb", model)
    _lab_nwb(tmp_path / "short.nwb", columns, short=("a_v",))
    with pytest.raises(ValueError, match=r"series 'a_v' has (\d+) values at \1 times, not at the"):
        read_trials(tmp_path / "short.nwb", model)


def test_an_nwb_series_reads_as_data_times_conversion_plus_offset(tmp_path):
    """Positions in cm from an origin 0.5 m off the task's (NWB's ``offset``) read in metres
    from the task's origin: the offset added after the conversion, not before, nor dropped."""
    from irc_torchrl.data.io import trials_to_columns

    model = Firefly2DModel()
    columns = trials_to_columns(_numbered(model, [3.0, 5.0]), model)
    _lab_nwb(tmp_path / "plain.nwb", columns)
    _lab_nwb(tmp_path / "offset.nwb", columns, centimetres=True, offset=0.5)
    expected = read_trials(tmp_path / "plain.nwb", model)
    back = read_trials(tmp_path / "offset.nwb", model)
    torch.testing.assert_close(back["state"], expected["state"], rtol=0, atol=1e-6)
    assert torch.equal(back["mask"], expected["mask"])


@pytest.mark.parametrize(
    "unit, kind, factor",
    [
        ("metres", "distance", 1.0),
        ("centimeters", "distance", 0.01),
        ("mm", "distance", 0.001),
        ("cm s^-1", "distance/s", 0.01),
        ("centimeters per second", "distance/s", 0.01),
        ("°", "rad", math.pi / 180),
        ("degrees/second", "rad/s", math.pi / 180),
        ("rad/s", "rad/s", 1.0),
        ("SI", "rad/s", 1.0),
        ("distance/s", "distance/s", 1.0),
    ],
)
def test_an_nwb_unit_is_read_however_spelled(unit, kind, factor):
    from irc_torchrl.data.nwb import unit_scale

    assert unit_scale(unit, kind, "f.nwb: series 'v'") == pytest.approx(factor, rel=1e-12)


@pytest.mark.parametrize(
    "unit, kind",
    [("cm/s", "rad/s"), ("cm", "rad"), ("pixels", "distance"), ("cm", "distance/s")],
)
def test_an_nwb_unit_of_another_kind_or_unknown_is_refused(unit, kind):
    """Read as the task's own they gave a file 100× off, or an angle in distance units."""
    from irc_torchrl.data.nwb import unit_scale

    with pytest.raises(ValueError, match=rf"f\.nwb: series 'v': unit '{unit}'; expected a {kind}"):
        unit_scale(unit, kind, "f.nwb: series 'v'")


def test_units_for_an_nwb_file_and_a_series_off_the_clock_are_refused(tmp_path):
    """NWB's series carry their unit: a units= on top converted them twice; a series on its own
    clock of the same length was aligned to the positions by index."""
    from irc_torchrl.data.io import trials_to_columns

    model = Firefly2DModel()
    columns = trials_to_columns(_numbered(model, [3.0, 5.0]), model)
    _lab_nwb(tmp_path / "cm.nwb", columns, cm_unit=True)
    with pytest.raises(ValueError, match=r"cm\.nwb: units: an NWB series carries its own unit"):
        read_trials(tmp_path / "cm.nwb", model, units={"x": "cm", "target_x": "cm"})


def test_an_nwb_files_targets_in_cm_are_read_as_declared(tmp_path):
    """Its trials table carries no unit: targets in cm were refused as a unit mistake whose
    advice (units.target_x=cm) was refused in turn, as units= for an NWB file."""
    from irc_torchrl.data.io import trials_to_columns

    model = Firefly2DModel()
    columns = trials_to_columns(_numbered(model, [3.0, 5.0]), model)
    _lab_nwb(tmp_path / "plain.nwb", columns)
    _lab_nwb(tmp_path / "targets.nwb", columns, cm_unit=True, targets_cm=True)
    with pytest.raises(ValueError, match=r"A unit mistake\? Declare it: units\.target_x=cm"):
        read_trials(tmp_path / "targets.nwb", model)
    back = read_trials(tmp_path / "targets.nwb", model, units={"target_x": "cm", "target_y": "cm"})
    expected = read_trials(tmp_path / "plain.nwb", model)
    torch.testing.assert_close(back["target"], expected["target"])
    torch.testing.assert_close(back["state"], expected["state"])


def test_an_nwb_file_too_long_is_not_sent_to_a_time_unit_it_cannot_take(tmp_path):
    """NWB's times are seconds: the "time in ms?" hint sent the user to units.time=ms, which
    an NWB file refuses."""
    from irc_torchrl.data.io import trials_to_columns

    model = Firefly2DModel()
    columns = trials_to_columns(_numbered(model, [3.0, 5.0]), model)
    columns["time"] = columns["time"] * 1000
    _lab_nwb(tmp_path / "ms.nwb", columns)
    with pytest.raises(ValueError, match=r"samples, .* so cut or drop longer trials$"):
        read_trials(tmp_path / "ms.nwb", model)
    _lab_nwb(tmp_path / "late.nwb", columns, late=("a_w",))
    with pytest.raises(ValueError, match=r"'a_w' has (\d+) values at \1 times, not at the \1 "):
        read_trials(tmp_path / "late.nwb", model)
