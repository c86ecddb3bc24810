"""Recorded trials in and out: round trips, resampling, units, and every malformed input refused."""

from __future__ import annotations

import csv
import gzip
import math
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.data.io import read_trials, trials_to_columns, write_trials
from irc_torchrl.data.trajectories import recorded_stops
from irc_torchrl.data.validate import check_stops
from irc_torchrl.envs import Firefly1DModel, Firefly2DModel
from irc_torchrl.envs.firefly1d import LEFT, STOP


def _simulated(model, n_agents: int, seed: int) -> TensorDict:
    """Random-action trials ``[n, T]`` with at least two recorded steps each."""
    theta = model.theta_space.sample((n_agents,), generator=torch.Generator().manual_seed(seed))
    trials = simulate_agents(model, None, theta, 4, model.theta_space.default(), seed=seed)
    trials = trials.reshape(-1, trials.shape[-1])
    return trials[trials["mask"].sum(-1) >= 2]


@pytest.fixture(scope="module")
def model2d():
    return Firefly2DModel()


@pytest.fixture(scope="module")
def model1d():
    return Firefly1DModel()


@pytest.fixture(scope="module")
def trials2d(model2d):
    return _simulated(model2d, 2, seed=0)


@pytest.fixture(scope="module")
def trials1d(model1d):
    return _simulated(model1d, 3, seed=1)


def _write_raw(columns: dict[str, np.ndarray], path) -> None:
    """A recording as a user would export it: NPZ arrays or a CSV, one row per step."""
    if path.suffix == ".npz":
        np.savez(path, **columns)
        return
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(list(columns))
        writer.writerows(zip(*(c.tolist() for c in columns.values()), strict=True))


def _write_recording(columns: dict[str, np.ndarray], path) -> Path:
    _write_raw(columns, path)
    return path


def _assert_same(back: TensorDict, trials: TensorDict) -> None:
    """Equal recorded steps, equal masks, and padding only beyond the longest trial."""
    steps = back.shape[-1]
    assert steps == int(trials["mask"].sum(-1).max())
    assert torch.equal(back["mask"], trials["mask"][:, :steps])
    mask = back["mask"]
    for key in ("state", "action", "target", "task_theta"):
        expected = trials[key][:, :steps][mask].double()
        assert torch.allclose(back[key][mask].double(), expected, atol=1e-5), key
    assert back["action"].dtype == trials["action"].dtype


def _hand_made(labels, steps=12, *, dt=0.1, start=0.0, jitter=0.0, heading=0.3, speed=0.5):
    """A recording made by hand, one row per step, every value known: in each trial the agent
    runs at ``speed`` along ``heading`` (one angle, or one per step), its positions stepped
    from its headings as the task steps them; trial ``i`` starts ``i`` m east at time
    ``start + 10 i`` s, its times ``jitter`` s off the grid at most."""
    rng = np.random.default_rng(0)
    rows: dict[str, list[np.ndarray]] = {}
    for i, label in enumerate(labels):
        time = start + 10.0 * i + dt * np.arange(steps) + jitter * rng.uniform(-1, 1, steps)
        angle = np.broadcast_to(np.asarray(heading, dtype=np.float64), (steps,))
        step = speed * np.diff(time)
        trial = {
            "trial": np.full(steps, label, dtype=np.float64),
            "time": time,
            "x": float(i) + np.concatenate([[0.0], np.cumsum(step * np.cos(angle[:-1]))]),
            "y": np.concatenate([[0.0], np.cumsum(step * np.sin(angle[:-1]))]),
            "heading": angle.copy(),
            "v": np.full(steps, speed),
            "w": np.zeros(steps),
            "a_v": np.full(steps, speed / 1.2),  # g_v's default
            "a_w": np.zeros(steps),
            "target_x": np.full(steps, 1.0 + i),
            "target_y": np.full(steps, 0.5),
        }
        for name, value in trial.items():
            rows.setdefault(name, []).append(value)
    return {name: np.concatenate(value) for name, value in rows.items()}


# --- round trips -----------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".npz", ".csv", ".csv.gz", "", ".nwb"])
def test_round_trip_preserves_values_mask_and_padding(tmp_path, model2d, trials2d, suffix):
    if suffix == ".nwb":
        pytest.importorskip("pynwb")
    path = tmp_path / f"trials{suffix}"
    write_trials(trials2d, path, model2d)
    back = read_trials(path, model2d)
    _assert_same(back, trials2d)
    steps = (torch.arange(back.shape[-1]) * model2d.dt).expand(back.shape)
    assert torch.allclose(back["time"][back["mask"]], steps[back["mask"]])
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


@pytest.mark.parametrize("suffix", [".npz", ".csv", ".csv.gz", "", ".nwb"])
def test_a_round_trip_is_bit_for_bit_and_pads_with_each_trials_last_step(
    tmp_path, model2d, trials2d, suffix
):
    """Written then read, every recorded value is the same float32 (a CSV at fewer than 9
    digits was not), each trial's own θ included (not the space's default), and each trial
    is padded by repeating its last step, as documented."""
    if suffix == ".nwb":
        pytest.importorskip("pynwb")
    trials = trials2d.clone()
    theta = model2d.theta_space.sample((len(trials),), generator=torch.Generator().manual_seed(3))
    trials["task_theta"] = theta.float()[:, None].expand(trials.shape + theta.shape[-1:])
    back = read_trials(write_trials(trials, tmp_path / f"t{suffix}", model2d), model2d)
    mask, lengths = back["mask"], back["mask"].sum(-1)
    assert torch.equal(mask, trials["mask"][:, : back.shape[-1]])
    assert torch.equal(back["trial"][:, 0], torch.arange(len(trials)))
    for key in ("state", "action", "target", "task_theta"):
        assert torch.equal(back[key][mask], trials[key][:, : back.shape[-1]][mask]), key
        for i, n in enumerate(lengths.tolist()):
            assert (back[key][i, n:] == back[key][i, n - 1]).all(), (key, i)


def test_round_trip_of_discrete_actions_keeps_integers(tmp_path, model1d, trials1d):
    path = write_trials(trials1d, tmp_path / "trials.csv", model1d)
    _assert_same(read_trials(path, model1d), trials1d)


@pytest.mark.parametrize("suffix", [".npz", ".csv", ""])
def test_trials_of_one_step_round_trip(tmp_path, model1d, suffix):
    """A 1D agent may stop at its first step (its target inside its goal, or, as here, acting
    at random): a trial of one sample, which a recording must read back (they were refused as
    too short to have a time step)."""
    theta = model1d.theta_space.sample((3,), generator=torch.Generator().manual_seed(1))
    trials = simulate_agents(model1d, None, theta, 10, model1d.theta_space.default(), seed=1)
    trials = trials.reshape(-1, trials.shape[-1])
    assert (trials["mask"].sum(-1) == 1).sum() >= 5  # the case under test
    _assert_same(
        read_trials(write_trials(trials, tmp_path / f"t{suffix}", model1d), model1d), trials
    )
    # its samples read as half a model step apart, each trial resamples to every other
    # sample, and a one-sample trial stays one step
    columns = trials_to_columns(trials, model1d)
    columns["time"] = columns["time"] / 2
    _write_raw(columns, tmp_path / "half.csv")
    with pytest.warns(UserWarning, match="resampled every trial"):
        half = read_trials(tmp_path / "half.csv", model1d)
    assert torch.equal(half["mask"].sum(-1), (trials["mask"].sum(-1) - 1) // 2 + 1)
    assert recorded_stops(half, model1d).any(-1).all()  # each trial's last action, its stop


def test_missing_theta_columns_take_the_space_default(tmp_path, model2d, trials2d):
    columns = trials_to_columns(trials2d, model2d)
    columns = {k: v for k, v in columns.items() if not k.startswith("theta.")}
    columns["theta.g_v"] = np.full(len(columns["trial"]), 1.5)
    _write_raw(columns, tmp_path / "t.csv")
    theta = read_trials(tmp_path / "t.csv", model2d)["task_theta"][0, 0]
    expected = model2d.theta_space.from_dict({"g_v": 1.5})
    assert torch.allclose(theta, expected)


def test_the_documented_csv_example_reads(tmp_path, model2d):
    doc = (Path(__file__).parents[1] / "docs" / "trajectory_schema.md").read_text()
    example = doc.split("```csv\n")[1].split("```")[0]
    (tmp_path / "example.csv").write_text(example)
    trials = read_trials(tmp_path / "example.csv", model2d)
    assert trials.shape == (1, 4)
    assert trials["task_theta"][0, 0, model2d.theta_space.index("g_v")] == pytest.approx(1.2)


@pytest.mark.parametrize("suffix", [".npz", ".csv"])
def test_columns_outside_the_schema_are_not_read(tmp_path, model2d, trials2d, suffix):
    """An export with more than the schema (eye position with gaps, event labels, a column of
    another length, a trailing comma's nameless column) reads as the schema's columns alone."""
    columns = trials_to_columns(trials2d, model2d)
    clean = tmp_path / f"clean{suffix}"
    _write_raw(columns, clean)
    rows = len(columns["trial"])
    eye = np.arange(rows, dtype=np.float64)
    eye[3] = np.nan
    extra = {**columns, "eye_x": eye, "event": np.array(["go"] * rows)}
    if suffix == ".npz":
        extra["events"] = np.arange(3.0)
    else:
        extra[""] = np.full(rows, "")
    path = tmp_path / f"extra{suffix}"
    _write_raw(extra, path)
    back, expected = read_trials(path, model2d), read_trials(clean, model2d)
    assert set(back.keys()) == set(expected.keys())
    for key in expected.keys():
        assert torch.equal(back[key], expected[key]), key


def test_a_column_named_twice_is_refused(tmp_path, model2d, trials2d):
    path = tmp_path / "twice.csv"
    _write_raw(trials_to_columns(trials2d, model2d), path)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0] + ",x", *(line + ",999" for line in lines[1:])]))
    with pytest.raises(ValueError, match=r"twice\.csv: column\(s\) \['x'\] appear more than once"):
        read_trials(path, model2d)


def test_a_gap_in_a_trial_is_refused_unless_resampled(tmp_path, model2d, trials2d):
    """Each kept sample is one model step, so missing samples would shorten the trial's time
    silently; resampling interpolates across them instead."""
    columns = trials_to_columns(trials2d, model2d)
    longest = int(np.bincount(columns["trial"].astype(np.int64)).argmax())
    drop = np.flatnonzero(columns["trial"] == longest)[2:4]
    keep = np.ones(len(columns["trial"]), dtype=bool)
    keep[drop] = False
    path = tmp_path / "gap.csv"
    _write_raw({k: v[keep] for k, v in columns.items()}, path)
    with pytest.raises(
        ValueError,
        match=rf"gap\.csv: trial {longest}, field 'time': time jumps from 0\.1 s to 0\.4 s "
        r"at sample 2, more than 1\.5 steps of 0\.1 s",
    ):
        read_trials(path, model2d)
    # the same recording at another rate is resampled, and the gap with it
    slow = {k: v[keep] for k, v in columns.items()}
    slow["time"] = slow["time"] * 2
    _write_raw(slow, path)
    with pytest.warns(UserWarning, match="resampled every trial") as caught:
        read = read_trials(path, model2d)
    assert read["mask"].sum() > keep.sum()
    assert [str(w.message).split(": ", 1)[1] for w in caught if "across" in str(w.message)] == [
        f"trial {longest}: a gap of 0.6 s from 0.2 s was interpolated across (1 model step, "
        "actions included, made up; the longest such gap of the recording): cut the trial "
        "there if the agent was not tracked"
    ]
    # one frame missing from a recording twice the model's rate makes up no model step
    fine = _oversampled(columns)
    keep = np.ones(len(fine["trial"]), dtype=bool)
    keep[np.flatnonzero(fine["trial"] == longest)[3]] = False
    _write_raw({k: v[keep] for k, v in fine.items()}, path)
    with pytest.warns(UserWarning, match="resampled every trial") as caught:
        read_trials(path, model2d)
    assert not [w for w in caught if "interpolated across" in str(w.message)]


@pytest.mark.parametrize(
    "field, change, match",
    [
        ("state", lambda t: t["state"][..., :4], r"'state' expected shape \[.*, T, 5\], got"),
        ("state", lambda t: torch.cat([t["state"], t["state"][..., :1]], -1), r"'state' expected"),
        ("mask", lambda t: torch.cat([~t["mask"][:1], t["mask"][1:]]), r"'mask' marks no step"),
    ],
    ids=["4 state columns", "6 state columns", "an empty trial"],
)
def test_a_memmap_folder_is_checked_as_held_trials(
    tmp_path, model2d, trials2d, field, change, match
):
    held = trials2d.select("state", "action", "target", "mask", "task_theta")
    fields = {key: held[key] for key in held.keys()}
    fields[field] = change(held)
    TensorDict(fields, batch_size=held.batch_size).memmap(tmp_path / "held")
    with pytest.raises(ValueError, match=match) as excinfo:
        read_trials(tmp_path / "held", model2d)
    assert str(tmp_path / "held") in str(excinfo.value)


def test_a_gap_is_measured_in_the_recordings_own_step_not_the_models(tmp_path, model2d):
    """At twice the model's rate one lost sample is a gap (two of its steps; one model step);
    at half its rate every step is two model steps, and none of them a gap."""
    fine = _hand_made([0], steps=24, dt=model2d.dt / 2)
    kept = np.arange(24) != 10
    path = _write_recording({k: v[kept] for k, v in fine.items()}, tmp_path / "fine.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # kept as recorded, off the model's step
        with pytest.raises(ValueError, match="time jumps from 0.45 s to 0.55 s"):
            read_trials(path, model2d, resample=False)
    coarse = _hand_made([0], steps=8, dt=2 * model2d.dt)
    path = _write_recording(coarse, tmp_path / "coarse.csv")
    with pytest.warns(UserWarning, match="kept as recorded"):
        assert read_trials(path, model2d, resample=False).shape[-1] == 8


def test_a_trial_cut_before_its_stop_reads_without_a_stop_warning(tmp_path, model2d):
    """A recording ending while the agent still runs has no stop to go on past."""
    path = _write_recording(_hand_made([0]), tmp_path / "running.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert int(read_trials(path, model2d)["mask"].sum()) == 12


def test_a_memmap_folder_of_several_agents_is_refused(tmp_path, model2d, trials2d):
    # irc recover's trials/ is [agent, trial, step]: pooled, they would read as one agent
    held = trials2d.select("state", "action", "target", "mask", "task_theta")
    torch.stack([held, held]).memmap(tmp_path / "agents")
    with pytest.raises(ValueError, match="holds the trials of 2 agents"):
        read_trials(tmp_path / "agents", model2d)


# --- resampling and units --------------------------------------------------------------------
def _oversampled(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each trial recorded twice as often: linear in between, actions held from the last step."""
    out: dict[str, list[np.ndarray]] = {k: [] for k in columns}
    for label in np.unique(columns["trial"]):
        rows = columns["trial"] == label
        time = columns["time"][rows].astype(np.float64)
        fine = np.linspace(time[0], time[-1], 2 * len(time) - 1)
        held = np.searchsorted(time, fine + 1e-9, side="right") - 1  # linspace's rounding
        for key, values in columns.items():
            held_key = key in ("trial", "a_v", "a_w", "action")
            out[key].append(values[rows][held] if held_key else np.interp(fine, time, values[rows]))
    return {k: np.concatenate(v) for k, v in out.items()}


def test_an_oversampled_recording_is_resampled_to_the_model_grid(tmp_path, model2d, trials2d):
    columns = _oversampled(trials_to_columns(trials2d, model2d))
    _write_raw(columns, tmp_path / "fine.npz")
    with pytest.warns(UserWarning, match="resampled every trial from a median time step of 0.05"):
        back = read_trials(tmp_path / "fine.npz", model2d)
    _assert_same(back, trials2d)


def test_resample_false_keeps_the_recording_and_warns(tmp_path, model2d, trials2d):
    columns = _oversampled(trials_to_columns(trials2d, model2d))
    _write_raw(columns, tmp_path / "fine.npz")
    with pytest.warns(UserWarning, match="kept as recorded"):
        back = read_trials(tmp_path / "fine.npz", model2d, resample=False)
    assert back.shape[-1] == 2 * trials2d["mask"].sum(-1).max() - 1


def test_an_oversampled_recording_of_discrete_actions_keeps_each_steps_action(
    tmp_path, model1d, trials1d
):
    """Resampled, a discrete action is the sample's at or before each model step, not the one
    half a step earlier (the previous step's action)."""
    _write_raw(_oversampled(trials_to_columns(trials1d, model1d)), tmp_path / "fine.csv")
    with pytest.warns(UserWarning, match="resampled every trial from a median time step of 0.5"):
        back = read_trials(tmp_path / "fine.csv", model1d)
    _assert_same(back, trials1d)


def test_an_agent_recorded_acting_twice_a_step_reads_with_the_action_at_each_steps_time(
    tmp_path, model1d
):
    """Resampled, a discrete action is the sample's at (or else before) each model step's
    time: right at every whole second, never the stop taken half a second later, even where
    the session clock (from 3.3 s) puts the sample a hair past the second."""
    time = 0.5 * np.arange(16)
    action = np.where(time % 1 == 0, 2, 1)  # right, then stop, every second
    x = np.concatenate([[0.0], np.cumsum(0.5 * (action[:-1] - 1))])  # g_a = 1
    columns = {"trial": np.zeros(16), "time": 3.3 + time, "x": x, "action": action}
    columns["target_x"] = np.full(16, 5.0)
    assert (columns["time"][::2] - 3.3 > np.arange(8)).any()  # the hair past
    with pytest.warns(UserWarning, match="resampled"):
        back = read_trials(_write_recording(columns, tmp_path / "twice.csv"), model1d)
    # but the last step's, which takes the trial's last recorded action (here the stop 7.5 s
    # in: a trial ends at its stop)
    assert back["action"].tolist() == [[2] * 7 + [1]]
    np.testing.assert_allclose(back["state"][0, :, 0].numpy(), 0.5 * np.arange(8), atol=1e-6)


def test_a_recording_five_percent_off_the_model_step_is_resampled_linearly(tmp_path, model2d):
    """A rig stepping 0.095 s is put on the 0.1 s grid (not read as 0.1 s steps), and a
    continuous action ramping in time reads as the ramp at the grid's times, not a sample's."""
    columns = _hand_made([0], steps=21, dt=0.095)
    columns["a_v"] = 0.2 + 0.25 * columns["time"]
    _write_raw(columns, tmp_path / "rig.csv")
    with pytest.warns(UserWarning, match="from a median time step of 0.095 s to the model's 0.1"):
        back = read_trials(tmp_path / "rig.csv", model2d)
    grid = 0.1 * np.arange(20)  # 1.9 s of the 1.9 s recorded
    assert back.shape == (1, 20)
    np.testing.assert_allclose(back["time"][0].numpy(), grid, atol=1e-6)
    np.testing.assert_allclose(back["action"][0, :, 0].numpy(), 0.2 + 0.25 * grid, atol=1e-6)
    np.testing.assert_allclose(back["state"][0, :, 0].numpy(), 0.5 * np.cos(0.3) * grid, atol=1e-6)


@pytest.mark.parametrize("late", [0.0, 0.05])
def test_a_trial_resampled_off_its_grid_keeps_its_last_sample_the_stop(tmp_path, model2d, late):
    """A 60 Hz rig whose trial ends (at the stop) between two steps of the 0.1 s grid lost
    every sample after the grid's last step before it: the stop. The last step now takes the
    trial's last recorded action; no step is added (a rig holding each action for its step
    reads as before)."""
    columns = _hand_made([0, 1], steps=80, dt=1 / 60, start=late)
    columns["a_v"][79::80] = 0.0  # each trial stops at its last sample, 79/60 s in
    _write_raw(columns, tmp_path / "rig.csv")
    with pytest.warns(UserWarning, match="resampled every trial"):
        back = read_trials(tmp_path / "rig.csv", model2d)
    assert back.shape == (2, 14)  # 1.3167 s: the steps at 0, 0.1, ..., 1.3 s
    assert recorded_stops(back, model2d)[:, -1].all()
    assert back["action"][:, -1, 0].tolist() == [0.0, 0.0]
    torch.testing.assert_close(back["action"][:, -2, 0], torch.full((2,), 0.5 / 1.2))


def test_a_discrete_trial_that_times_out_without_a_stop_is_no_stop_with_steps_after(model1d):
    """A 1D trial that ran out of steps moving (no STOP) is a trial like any other; read as a
    stop at step 0, it was refused as 'stops 0 s into it, yet 4 steps follow'."""
    steps = 5
    held = TensorDict(
        {
            "action": torch.full((2, steps), LEFT),
            "mask": torch.ones(2, steps, dtype=torch.bool),
            "trial": torch.arange(2).unsqueeze(-1).expand(2, steps),
            "time": torch.arange(steps, dtype=torch.float32).expand(2, steps) * model1d.dt,
        },
        batch_size=[2, steps],
    )
    held["action"][1, -1] = STOP  # the other one stops on its last step
    check_stops(held, model1d, "session.csv")


def test_a_discrete_stop_between_two_model_steps_is_kept(tmp_path, model1d):
    """Sampled every half step, a trial of 'left' then a stop half a step later read as one
    step of 'left': the stop was dropped, and nothing was said. A trial ends at its stop,
    which its last step takes."""
    columns = {
        "trial": np.array([0.0, 0.0, 1.0, 1.0, 1.0]),
        "time": np.array([0.0, 0.5, 10.0, 10.5, 11.0]),
        "x": np.array([0.0, -0.5, 0.0, 0.5, 1.0]),
        "action": np.array([0, 1, 2, 2, 1]),
        "target_x": np.array([2.0, 2.0, 2.0, 2.0, 2.0]),
    }
    with pytest.warns(UserWarning, match="resampled every trial"):
        back = read_trials(_write_recording(columns, tmp_path / "half.csv"), model1d)
    assert back["mask"].sum(-1).tolist() == [1, 2]
    assert back["action"][0, 0] == 1 and back["action"][1].tolist() == [2, 1]


def test_the_same_recording_in_m_cm_and_mm_reads_alike(tmp_path, model2d):
    """Positions, targets, speeds and θ columns in cm or mm (time in ms, angular speeds in
    degrees) declared so read as in metres (θ columns' units were refused as unknown)."""
    metres = _hand_made([0, 1])
    rows = len(metres["time"])
    metres |= {"theta.g_v": np.full(rows, 1.3), "theta.goal_radius": np.full(rows, 0.45)}
    metres["theta.g_w"] = np.full(rows, 1.1)
    distances = ("x", "y", "target_x", "target_y", "theta.goal_radius", "v", "theta.g_v")
    expected = read_trials(_write_recording(metres, tmp_path / "m.csv"), model2d)
    for unit, factor in (("cm", 100.0), ("mm", 1000.0)):
        columns = {k: v * factor if k in distances else v for k, v in metres.items()}
        columns["time"] = metres["time"] * 1000.0
        columns["theta.g_w"] = np.degrees(metres["theta.g_w"])
        units = {k: unit for k in distances[:5]} | {k: f"{unit}/s" for k in distances[5:]}
        units |= {"time": "ms", "theta.g_w": "deg/s"}
        back = read_trials(
            _write_recording(columns, tmp_path / f"{unit}.csv"), model2d, units=units
        )
        for key in ("state", "target", "time", "mask", "task_theta"):
            torch.testing.assert_close(back[key], expected[key], rtol=1e-6, atol=1e-6, msg=key)


def test_positions_in_mm_declared_as_cm_are_refused(tmp_path, model2d):
    """Read 10× too far, every column stays within the θ space's reach; only the steps'
    regression on the velocity says so (a slope threshold of 30 let it through)."""
    columns = _hand_made([0, 1])
    for key in ("x", "y", "target_x", "target_y"):
        columns[key] = columns[key] * 1000.0
    units = {k: "cm" for k in ("x", "y", "target_x", "target_y")}
    with pytest.raises(ValueError, match=r"field\(s\) 'x'/'y': each step moves 10× as far"):
        read_trials(_write_recording(columns, tmp_path / "mm.csv"), model2d, units=units)


def test_trials_keep_their_numbers_and_the_order_they_first_appear_in(tmp_path, model2d):
    """Trials 7, 3 and 5.5 read in that order (not sorted), numbered as recorded (5.5 not
    truncated to 5 beside the integers), each with its own rows."""
    back = read_trials(_write_recording(_hand_made([7, 3, 5.5]), tmp_path / "t.csv"), model2d)
    assert back["trial"].dtype == torch.float64
    assert back["trial"][:, 0].tolist() == [7.0, 3.0, 5.5]
    assert back["state"][:, 0, 0].tolist() == [0.0, 1.0, 2.0]  # trial i starts i m east
    assert back["target"][:, 0, 0].tolist() == [1.0, 2.0, 3.0]


def test_time_counts_from_each_trials_first_sample_as_recorded(tmp_path, model2d):
    """A session clock (trials from 12.3 s and 22.3 s) reads as seconds since each trial's
    start, the recorded jitter kept, not replaced by the model's grid."""
    columns = _hand_made([0, 1], start=12.3, jitter=4e-4)
    back = read_trials(_write_recording(columns, tmp_path / "t.csv"), model2d)
    for i in range(2):
        time = columns["time"][columns["trial"] == i]
        assert torch.equal(back["time"][i], torch.tensor(time - time[0], dtype=torch.float32))


@pytest.mark.parametrize(
    "before, after",
    [(3.0, -1.2), (3.5, -2.75)],
    ids=["a turn of 2.1 rad in one sample", "a sign flip beyond ±π"],
)
def test_a_jump_across_plus_minus_pi_that_is_no_wrap_is_refused(tmp_path, model2d, before, after):
    """Only an atan2 wrap (within ±π on both sides, under π/2 once 2π is taken off) is
    unwrapped; a tracker's glitch is refused, not smoothed into a turn the agent never made."""
    heading = np.where(np.arange(12) < 6, before, after)
    path = _write_recording(_hand_made([0], heading=heading), tmp_path / "glitch.csv")
    with pytest.raises(ValueError, match=r"trial 0, field 'heading': changes by .* at time 0\.6 s"):
        read_trials(path, model2d)


def test_a_trial_longer_than_the_task_allows_is_refused_naming_it(tmp_path, model2d, trials2d):
    columns = trials_to_columns(trials2d, model2d)
    first = columns["trial"] == columns["trial"][0]
    rows = {k: v[first] for k, v in columns.items()}
    extra = model2d.max_steps + 1 - len(rows["time"])  # the agent stands still for the rest
    longer = {k: np.concatenate([v, np.repeat(v[-1:], extra)]) for k, v in rows.items()}
    longer["time"] = model2d.dt * np.arange(model2d.max_steps + 1)
    _write_raw(longer, tmp_path / "long.csv")
    label = int(columns["trial"][0])
    with pytest.raises(
        ValueError, match=f"long.csv: trial {label}, field 'time': {model2d.max_steps + 1} samples"
    ):
        read_trials(tmp_path / "long.csv", model2d)


def test_a_recording_on_the_model_grid_is_not_resampled(tmp_path, model2d, trials2d):
    write_trials(trials2d, tmp_path / "t.npz", model2d)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_trials(tmp_path / "t.npz", model2d)


def test_units_are_converted_to_the_model_units(tmp_path, model2d, trials2d):
    columns = trials_to_columns(trials2d, model2d)
    scale = {"x": 100, "y": 100, "target_x": 100, "target_y": 100, "v": 100}
    scale.update({"heading": 180 / math.pi, "w": 180 / math.pi, "time": 1000})
    for key, factor in scale.items():
        columns[key] = columns[key].astype(np.float64) * factor
    _write_raw(columns, tmp_path / "lab.csv")
    units = {"x": "cm", "y": "cm", "target_x": "cm", "target_y": "cm", "v": "cm/s"}
    units.update({"heading": "deg", "w": "deg/s", "time": "ms"})
    _assert_same(read_trials(tmp_path / "lab.csv", model2d, units=units), trials2d)


@pytest.mark.parametrize(
    "turn, wrapped, units, branch",
    [
        # the agent starts facing -x: atan2's heading crosses ±π
        (math.pi - 0.02, lambda h: np.angle(np.exp(1j * h)), {}, 0.0),
        # facing +x, a compass's 0–360° crosses 0 (it was refused, hinting at degrees)
        (-0.02, lambda h: np.degrees(np.mod(h, 2 * math.pi)), {"heading": "deg"}, 2 * math.pi),
    ],
)
def test_a_wrapped_heading_is_unwrapped(tmp_path, model2d, trials2d, turn, wrapped, units, branch):
    """An arena-frame recording (the task turned by ``turn``) whose heading is wrapped reads
    as the continuous heading the model steps, from the file's first value (``branch``: the
    2π it adds); positions and targets are kept as recorded."""
    cos, sin = math.cos(turn), math.sin(turn)
    columns = {k: v.astype(np.float64) for k, v in trials_to_columns(trials2d, model2d).items()}
    for x, y in (("x", "y"), ("target_x", "target_y")):
        a, b = columns[x], columns[y]
        columns[x], columns[y] = cos * a - sin * b, sin * a + cos * b
    columns["heading"] = wrapped(columns["heading"] + turn)
    assert (np.abs(np.diff(columns["heading"])) > math.pi).any()  # the file does wrap
    _write_raw(columns, tmp_path / "arena.csv")
    back = read_trials(tmp_path / "arena.csv", model2d, units=units)
    expected = trials2d.clone()
    state, target = expected["state"].double(), expected["target"].double()
    for part in (state, target):
        a, b = part[..., 0].clone(), part[..., 1].clone()
        part[..., 0], part[..., 1] = cos * a - sin * b, sin * a + cos * b
    state[..., 2] += turn + branch
    expected["state"], expected["target"] = state.float(), target.float()
    _assert_same(back, expected)


@pytest.mark.parametrize(
    "units, error, match",
    [
        ({"x": "inch"}, ValueError, r"unknown unit 'inch' for column 'x'.*m, cm, mm"),
        ({"heading": "cm"}, ValueError, r"'heading' \(model unit rad\); expected one of rad, deg"),
        ({"a_v": "m/s"}, KeyError, r"column 'a_v' has no unit.*actions are dimensionless"),
    ],
)
def test_unit_mistakes_in_the_units_argument(tmp_path, model2d, trials2d, units, error, match):
    path = write_trials(trials2d, tmp_path / "t.npz", model2d)
    with pytest.raises(error, match=match):
        read_trials(path, model2d, units=units)


def test_custom_time_and_trial_column_names(tmp_path, model2d, trials2d):
    columns = trials_to_columns(trials2d, model2d, time_column="t_s", trial_column="trial_id")
    _write_raw(columns, tmp_path / "t.csv")
    back = read_trials(tmp_path / "t.csv", model2d, time_column="t_s", trial_column="trial_id")
    _assert_same(back, trials2d)


# --- malformed recordings --------------------------------------------------------------------
def _rows(columns, trial: int) -> np.ndarray:
    return np.flatnonzero(columns["trial"] == trial)


def _set(trial: int, sample: int, field: str, value: float):
    def corrupt(columns):
        columns[field] = columns[field].astype(np.float64)
        columns[field][_rows(columns, trial)[sample]] = value
        return columns

    return corrupt


def _blank(trial: int, sample: int, field: str):
    def corrupt(columns):  # an empty CSV cell, as a spreadsheet exports a missing value
        columns[field] = columns[field].astype(object)
        columns[field][_rows(columns, trial)[sample]] = ""
        return columns

    return corrupt


def _shift(trial: int, sample: int, field: str, by: float):
    def corrupt(columns):
        columns[field] = columns[field].astype(np.float64)
        columns[field][_rows(columns, trial)[sample]] += by
        return columns

    return corrupt


def _scale(factor: float, *fields: str):
    def corrupt(columns):
        for field in fields:
            columns[field] = columns[field] * factor
        return columns

    return corrupt


def _fast_in_cm(columns):
    """Positions in cm of a recording sampled at 1 kHz (a fast rig, no time unit mistake)."""
    columns = _scale(100.0, "x", "y")(columns)
    columns["time"] = columns["time"] / 100
    return columns


def _rename(old: str, new: str | None):
    def corrupt(columns):
        value = columns.pop(old)
        if new is not None:
            columns[new] = value
        return columns

    return corrupt


def _swap_times(columns):
    rows = _rows(columns, 2)
    columns["time"][rows[[1, 2]]] = columns["time"][rows[[2, 1]]]
    return columns


def _pooled(columns):
    """Two sessions in one file, numbering their trials alike."""
    return {k: np.concatenate([v, v]) for k, v in columns.items()}


def _repeat_time(columns):
    rows = _rows(columns, 3)
    columns["time"][rows[2]] = columns["time"][rows[1]]
    return columns


def _short_column(columns):
    columns["y"] = columns["y"][:-3]
    return columns


def _theta_column(name: str, value: float):
    def corrupt(columns):
        columns[name] = np.full(len(columns["trial"]), value)
        return columns

    return corrupt


def _number_as_previous(trial: int):
    """Trial ``trial`` numbered as the one before it (an export's counter that missed one)."""

    def corrupt(columns):
        columns["trial"][_rows(columns, trial)] = trial - 1
        return columns

    return corrupt


def _no_rows(columns):
    return {k: v[:0] for k, v in columns.items()}


def _matrix_column(columns):
    columns["x"] = np.stack([columns["x"], columns["x"]], -1)
    return columns


# (case, task, format, corruption, error, what the message must say)
MALFORMED = [
    ("nan gap in x", "2d", ".csv", _set(1, 2, "x", np.nan), ValueError,
     r"trial 1, field 'x': nan at time 0\.2 s \(sample 2\); expected finite"),
    ("blank cell in x", "2d", ".csv", _blank(1, 2, "x"), ValueError,
     r"trial 1, field 'x': nan at time 0\.2 s \(sample 2\); expected finite"),
    ("inf velocity", "2d", ".npz", _set(0, 1, "v", np.inf), ValueError,
     r"trial 0, field 'v': inf at time 0\.1 s"),
    ("nan time", "2d", ".npz", _set(1, 1, "time", np.nan), ValueError,
     r"trial 1, field 'time': nan at sample 1"),
    ("time goes back", "2d", ".csv", _swap_times, ValueError,
     r"trial 2, field 'time': time goes from 0\.2 s to 0\.1 s.*strictly increasing"),
    ("two sessions pooled", "2d", ".csv", _pooled, ValueError,
     r"field 'trial': trial 0 is on rows 1–\d+ and again from row \d+ \(the table's rows "
     r"counted from 1, after a CSV's header\); expected each trial's"),
    ("repeated time", "2d", ".csv", _repeat_time, ValueError,
     r"trial 3, field 'time': time goes from 0\.1 s to 0\.1 s at sample 2"),
    ("missing column", "2d", ".csv", _rename("heading", None), KeyError,
     r"missing column 'heading'; expected columns \['trial', 'time', 'x'"),
    ("misnamed state column", "2d", ".csv", _rename("heading", "headng"), KeyError,
     r"missing column 'heading'; column 'headng' looks like a misnamed 'heading'"),
    ("state column in capitals", "2d", ".csv", _rename("x", "X"), KeyError,
     r"missing column 'x'; column 'X' looks like a misnamed 'x'"),
    ("misnamed target column", "2d", ".npz", _rename("target_x", "targetX"), KeyError,
     r"column 'targetX' looks like a misnamed 'target_x'"),
    ("misnamed trial column", "1d", ".csv", _rename("trial", "trials"), KeyError,
     r"missing column 'trial'; column 'trials' looks like a misnamed 'trial' \(rename it, or "
     r"declare trial_column=trials\); expected"),
    ("misnamed time column", "2d", ".csv", _rename("time", "Time"), KeyError,
     r"column 'Time' looks like a misnamed 'time' \(rename it, or declare time_column=Time\)"),
    ("two trials under one number", "2d", ".csv", _number_as_previous(2), ValueError,
     r"trial 1, field 'time': time goes from [\d.]+ s to 0 s at sample \d+; expected strictly "
     r"increasing times \(it starts over: two trials under one number\?\)"),
    ("targets missing", "2d", ".csv", _rename("target_y", None), KeyError,
     r"missing column 'target_y'"),
    ("target missing in a trial", "2d", ".csv", _set(1, 0, "target_y", np.nan), ValueError,
     r"trial 1, field 'target_y': nan at time 0 s"),
    ("target moves", "2d", ".npz", _set(0, 2, "target_x", 9.0), ValueError,
     r"trial 0, field 'target_x': 9 at sample 2 differs from .*expected one value per trial"),
    ("target drifts by 5 mm", "2d", ".csv", _shift(0, 2, "target_x", 0.005), ValueError,
     r"trial 0, field 'target_x': .* at sample 2 differs from .*expected one value per trial"),
    ("ragged arrays", "2d", ".npz", _short_column, ValueError,
     r"column 'y' has \d+ values but column 'trial' has \d+; expected one value per time step"),
    ("2-D array", "2d", ".npz", _matrix_column, ValueError,
     r"column 'x' has shape \[\d+, 2\]; expected one value per time step"),
    ("control beyond bounds", "2d", ".csv", _set(1, 1, "a_w", 1.7), ValueError,
     r"trial 1, field 'a_w': 1\.7 at time 0\.1 s; expected a dimensionless control.*\[-1, 1\]"),
    ("control just beyond bounds", "2d", ".csv", _set(1, 1, "a_w", 1.01), ValueError,
     r"trial 1, field 'a_w': 1\.01 at time 0\.1 s; expected a dimensionless control"),
    ("action index 3", "1d", ".csv", _set(0, 1, "action", 3), ValueError,
     r"trial 0, field 'action': 3 at time 1 s; expected an action index, an integer in 0\.\.2"),
    ("fractional action", "1d", ".npz", _set(1, 0, "action", 1.5), ValueError,
     r"trial 1, field 'action': 1\.5 at time 0 s"),
    ("velocity in cm/s", "2d", ".csv", _scale(100.0, "v"), ValueError,
     r"trial \d+, field 'v': .* distance/s .*expected below 16 .*units=\{'v': 'cm/s'\}"),
    ("angular velocity in deg/s", "2d", ".npz", _scale(180 / math.pi, "w"), ValueError,
     r"trial \d+, field 'w': .* rad/s .*expected below 14 .*units=\{'w': 'deg/s'\}"),
    ("position in cm", "2d", ".csv", _scale(100.0, "x", "y"), ValueError,
     r"trial \d+, field 'x/y': the speed between samples of .*fastest\)\. A unit mistake\? "
     r"Declare them: units\.x=cm units\.y=cm \(irc fit\) or units=\{'x': 'cm', 'y': 'cm'\}"),
    ("seconds read as ms", "2d", ".csv", _scale(0.001, "time"), ValueError,
     r"field 'x/y': the speed between samples .*Times in seconds given units\.time=ms \(a "
     r"median step of 0\.0001 s against the task's 0\.1 s\)\? Drop it\. Or a unit mistake of "
     r"the positions\? Declare them: units\.x=cm units\.y=cm"),
    ("positions in cm sampled at 1 kHz", "2d", ".csv", _fast_in_cm, ValueError,
     r"field 'x/y': the speed between samples .*fastest\)\. A unit mistake\? Declare them"),
    ("1d position in cm", "1d", ".csv", _scale(100.0, "x"), ValueError,
     r"trial \d+, field 'x': the speed between samples .*expected below 15"),
    ("heading in degrees", "2d", ".csv", _scale(180 / math.pi, "heading"), ValueError,
     r"trial \d+, field 'heading': changes by .*expected < π per sample.*'deg'"),
    ("theta outside its space", "2d", ".csv", _theta_column("theta.goal_radius", 5.0), ValueError,
     r"trial 0, field 'theta.goal_radius': 5; expected a value in its space \[0.2, 0.5\]"),
    ("theta varies", "1d", ".npz", _set(1, 1, "theta.g_a", 0.7), ValueError,
     r"trial 1, field 'theta.g_a': 0\.7 at sample 1 differs"),
    ("misnamed theta", "2d", ".csv", _rename("theta.g_v", "theta.gv"), KeyError,
     r"column 'theta.gv' names no θ parameter; did you mean 'theta.g_v'\?"),
    ("nan trial number", "2d", ".csv", _set(1, 0, "trial", np.nan), ValueError,
     r"field 'trial' is nan at row \d+ \(the table's rows counted from 1, after a CSV's "
     r"header\); expected a trial number on every row"),
    ("no rows", "2d", ".csv", _no_rows, ValueError,
     r"the file holds no samples; expected one row per time step"),
    ("empty archive", "2d", ".npz", lambda c: {}, ValueError, r"the file holds no samples"),
]  # fmt: skip


@pytest.mark.parametrize(
    "task, suffix, corrupt, error, match",
    [case[1:] for case in MALFORMED],
    ids=[case[0] for case in MALFORMED],
)
def test_malformed_recordings_are_refused_naming_trial_and_field(
    tmp_path, model1d, model2d, trials1d, trials2d, task, suffix, corrupt, error, match
):
    model, trials = (model1d, trials1d) if task == "1d" else (model2d, trials2d)
    path = tmp_path / f"recording{suffix}"
    _write_raw(corrupt(trials_to_columns(trials, model)), path)
    with pytest.raises(error, match=match) as excinfo:
        read_trials(path, model)
    assert str(path) in str(excinfo.value)


@pytest.mark.parametrize(
    "name, content, error, match",
    [
        ("bad.npz", b"trial,time\n0,0\n", ValueError, r"not an NPZ archive"),
        ("bad.csv", b"\xff\xfe\x00\x81binary", ValueError, r"not a CSV text file"),
        ("empty.csv", b"", ValueError, r"the file holds no samples"),
        ("text.csv", b"trial,time,x\n0,0,1\n0,0.1,left\n", ValueError,
         r"line 3, column 'x': 'left' is not a number"),
        ("ragged.csv", b"trial,time,x\n0,0,1\n0,0.1\n", ValueError,
         r"line 3 has 2 values; expected 3"),
        ("blank.csv", b"trial,time,x\n\n0,0,1\n\n0,0.1,left\n", ValueError,
         r"line 5, column 'x': 'left' is not a number"),  # the file's line, blank ones counted
        ("data.txt", b"1 2 3\n", ValueError, r"unknown format '\.txt'; expected \.npz, \.csv"),
    ],
)  # fmt: skip
def test_files_that_are_not_what_their_suffix_says(tmp_path, model2d, name, content, error, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(error, match=match):
        read_trials(tmp_path / name, model2d)


def test_a_trial_on_two_blocks_of_rows_is_named_by_the_tables_rows_from_1(tmp_path, model1d):
    """The rows were counted from 0, where a spreadsheet counts from 1 (and the CSV reader's
    own messages give the file's lines)."""
    path = tmp_path / "pooled.csv"
    path.write_text("trial,time,x,action,target_x\n0,0,0,2,3\n0,1,1,2,3\n1,0,0,2,3\n0,2,2,1,3\n")
    message = r"trial 0 is on rows 1–2 and again from row 4 \(the table's rows counted from 1"
    with pytest.raises(ValueError, match=message):
        read_trials(path, model1d)


def test_an_npz_of_python_objects_is_refused_without_unpickling(tmp_path, model2d):
    np.savez(tmp_path / "objects.npz", trial=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="expected numeric arrays"):
        read_trials(tmp_path / "objects.npz", model2d)


def test_a_folder_that_is_not_a_memmap(tmp_path, model2d):
    (tmp_path / "folder").mkdir()
    with pytest.raises(ValueError, match="not a TensorDict memmap folder"):
        read_trials(tmp_path / "folder", model2d)
    for name in ("b.csv", "a.csv", "notes.txt"):  # a session's folder: its files, named
        (tmp_path / "folder" / name).write_text("trial,time\n")
    message = r"folder: a folder of recordings \(a.csv, b.csv\), not a .* give the files \(e.g. "
    with pytest.raises(ValueError, match=message + r".*folder/\*\.csv\)$"):
        read_trials(tmp_path / "folder", model2d)


def test_a_gzipped_csv_reads_as_its_csv_and_a_damaged_one_is_refused(tmp_path, model2d, trials2d):
    """A rig's compressed export (session.csv.gz) was refused as the unknown format '.gz'; it
    reads as the CSV inside, a folder of them is named as recordings, and gzip's own damage
    (a truncated download, a plain file so named) is one line naming the file."""
    plain = write_trials(trials2d, tmp_path / "a.csv", model2d)
    packed = write_trials(trials2d, tmp_path / "a.csv.gz", model2d)
    assert gzip.decompress(packed.read_bytes()) == plain.read_bytes()
    assert write_trials(trials2d, tmp_path / "b.csv.gz", model2d).read_bytes() == (
        packed.read_bytes()  # no time stamp in the header: the same trials, the same bytes
    )
    _assert_same(read_trials(packed, model2d), read_trials(plain, model2d))
    (tmp_path / "truncated.csv.gz").write_bytes(packed.read_bytes()[:200])
    (tmp_path / "plain.csv.gz").write_bytes(plain.read_bytes())
    for name in ("truncated.csv.gz", "plain.csv.gz"):
        with pytest.raises(ValueError, match=rf"^\S*{name}: a damaged gzip file \(.*\); write"):
            read_trials(tmp_path / name, model2d)
    (tmp_path / "session").mkdir()
    packed.rename(tmp_path / "session" / "a.csv.gz")
    with pytest.raises(
        ValueError, match=r"a folder of recordings \(a.csv.gz\).*session/\*\.csv\.gz\)$"
    ):
        read_trials(tmp_path / "session", model2d)


def test_a_missing_file(tmp_path, model2d):
    with pytest.raises(FileNotFoundError, match="no such file"):
        read_trials(tmp_path / "nothing.csv", model2d)


# --- NWB without pynwb, and atomic writes ----------------------------------------------------
def test_nwb_without_pynwb_says_how_to_install_it(tmp_path, model2d, monkeypatch):
    monkeypatch.setitem(sys.modules, "pynwb", None)
    monkeypatch.delitem(sys.modules, "irc_torchrl.data.nwb", raising=False)
    (tmp_path / "session.nwb").write_bytes(b"")
    with pytest.raises(ImportError, match=r"pip install 'irc-torchrl\[nwb\]'"):
        read_trials(tmp_path / "session.nwb", model2d)


def test_a_failing_file_write_leaves_neither_a_partial_nor_a_temp_file(
    tmp_path, model2d, trials2d, monkeypatch
):
    def fail(file, **arrays):
        file.write(b"PK partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", fail)
    with pytest.raises(OSError, match="disk full"):
        write_trials(trials2d, tmp_path / "t.npz", model2d)
    assert list(tmp_path.iterdir()) == []


def test_a_failing_folder_write_keeps_the_old_folder(tmp_path, model2d, trials2d, monkeypatch):
    path = write_trials(trials2d, tmp_path / "held", model2d)

    def fail(self, prefix, **kwargs):
        (prefix / "state.memmap").write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(TensorDict, "memmap", fail)
    with pytest.raises(OSError, match="disk full"):
        write_trials(trials2d[:2], path, model2d)
    assert [p.name for p in tmp_path.iterdir()] == ["held"]
    monkeypatch.undo()
    _assert_same(read_trials(path, model2d), trials2d)


# --- damaged files and spreadsheet exports ---------------------------------------------------
def test_a_truncated_memmap_file_is_refused_and_left_as_it_was(tmp_path, model2d, trials2d):
    path = write_trials(trials2d, tmp_path / "held", model2d)
    state = path / "state.memmap"
    state.write_bytes(state.read_bytes()[:1000])
    with pytest.raises(ValueError, match=r"state\.memmap: 1000 bytes; expected \d+ .*truncated"):
        read_trials(path, model2d)
    assert state.stat().st_size == 1000  # not grown back by opening it


def test_a_damaged_npz_archive_is_refused(tmp_path, model2d, trials2d):
    path = write_trials(trials2d, tmp_path / "t.npz", model2d)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3] ^= 0xFF  # a flipped byte inside a member: its checksum fails
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"t\.npz: a damaged NPZ archive"):
        read_trials(path, model2d)


def test_a_csv_with_excels_byte_order_mark_reads_as_without(tmp_path, model2d, trials2d):
    plain = write_trials(trials2d, tmp_path / "plain.csv", model2d)
    assert b"\r" not in plain.read_bytes()  # written with csv's default "\r\n" until 2026-12
    marked = tmp_path / "marked.csv"
    marked.write_bytes("\ufeff".encode() + plain.read_bytes())
    _assert_same(read_trials(marked, model2d), read_trials(plain, model2d))


def test_complex_and_zero_dimensional_columns_are_refused(tmp_path, model2d, trials2d):
    columns = trials_to_columns(trials2d, model2d)
    np.savez(tmp_path / "c.npz", **{**columns, "x": columns["x"] + 1j})
    with pytest.raises(ValueError, match=r"column 'x' holds complex\d+ values; expected numbers"):
        read_trials(tmp_path / "c.npz", model2d)
    np.savez(tmp_path / "s.npz", **{**columns, "trial": np.array(0)})
    with pytest.raises(ValueError, match=r"column 'trial' has shape \[\]; expected one value"):
        read_trials(tmp_path / "s.npz", model2d)


def test_a_written_folder_gets_the_mode_mkdir_would_give_it(tmp_path, model2d, trials2d):
    umask = os.umask(0o022)
    try:
        path = write_trials(trials2d, tmp_path / "held", model2d)
    finally:
        os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o755  # not mkdtemp's private 0o700


def test_decimal_trial_numbers_survive_and_round_off_at_the_action_bounds_is_clipped(
    tmp_path, model2d, trials2d
):
    """Session.trial numbers like 20240501.001 were all read as 20240502.0 (float32), and an
    action exported as 1.0000001 passed the reader's check but failed the trials' check."""
    columns = trials_to_columns(trials2d, model2d)
    columns["trial"] = 20240501 + columns["trial"].astype(np.float64) / 1000 + 0.001
    last = int(trials2d["mask"][0].sum()) - 1  # trial 0's last row of the table
    columns["a_w"] = columns["a_w"].astype(np.float64)
    columns["a_w"][last] = 1.0000001
    _write_raw(columns, tmp_path / "session.csv")
    back = read_trials(tmp_path / "session.csv", model2d)
    expected = 20240501 + torch.arange(trials2d.shape[0], dtype=torch.float64) / 1000 + 0.001
    assert back["trial"].dtype == torch.float64
    assert torch.equal(back["trial"][:, 0], expected)
    assert back["action"].max() <= 1.0 and back["action"][0, last, 1] == 1.0
    for suffix in (".csv", ".npz", ""):  # written and read back, they stay themselves
        again = read_trials(write_trials(back, tmp_path / f"again{suffix}", model2d), model2d)
        assert torch.equal(again["trial"], back["trial"])


def test_several_agents_are_refused_not_pooled_into_one_recording(tmp_path, model2d, trials2d):
    agents = torch.stack([trials2d, trials2d])
    for name in ("t.csv", "held"):
        with pytest.raises(ValueError, match=r"trials: holds the trials of 2 agents .*trials\[i\]"):
            write_trials(agents, tmp_path / name, model2d)
    assert list(tmp_path.iterdir()) == []
    path = write_trials(agents[:1], tmp_path / "t.csv", model2d)
    _assert_same(read_trials(path, model2d), trials2d)


@pytest.mark.parametrize(
    "scale, units, message",
    [
        # positions in cm, v in m/s declared as cm/s: each column within reach, v 100× slow
        (
            {"x": 100, "y": 100, "target_x": 100, "target_y": 100},
            {"x": "cm", "y": "cm", "target_x": "cm", "target_y": "cm", "v": "cm/s"},
            r"field\(s\) 'x'/'y': each step moves 10[01]× as far as the task's transition "
            r"predicts from 'v'",
        ),
        # heading in rad declared as degrees: it turns 57× less than w says
        ({}, {"heading": "deg"}, r"field\(s\) 'heading': each step moves 0\.017\d× as far"),
    ],
)
def test_a_velocity_in_another_unit_than_its_positions_is_refused(
    tmp_path, model2d, trials2d, scale, units, message
):
    """Every column alone was within the θ space's reach, so the fit ran and returned a
    confident, wrong θ̂ (obs σ_v 1.33 [1.25, 1.39] for a truth of 0.27)."""
    columns = trials_to_columns(trials2d, model2d)
    for key, factor in scale.items():
        columns[key] = columns[key].astype(np.float64) * factor
    _write_raw(columns, tmp_path / "lab.csv")
    with pytest.raises(ValueError, match=message):
        read_trials(tmp_path / "lab.csv", model2d, units=units)


def test_an_action_of_the_other_sign_is_refused_and_a_faster_rig_warned(
    tmp_path, model2d, trials2d
):
    """A joystick's other sign convention, or a rig 1.5× faster than the world's θ, passed
    every check and gave a converged, confident, wrong θ̂ (g_w on its bound, "identified")."""
    columns = trials_to_columns(trials2d, model2d)
    columns["a_w"] = -columns["a_w"].astype(np.float64)
    _write_raw(columns, tmp_path / "flipped.csv")
    with pytest.raises(ValueError, match=r"field\(s\) 'w': follow the actions -0\.9\d+× as str"):
        read_trials(tmp_path / "flipped.csv", model2d)
    columns = trials_to_columns(trials2d, model2d)
    for key in ("x", "y", "target_x", "target_y", "v"):  # all moves 1.5× as far
        columns[key] = columns[key].astype(np.float64) * 1.5
    _write_raw(columns, tmp_path / "fast.csv")
    with pytest.warns(UserWarning, match=r"'v': follow the actions 1\.5\d× as strongly .* the "):
        read_trials(tmp_path / "fast.csv", model2d)


@pytest.fixture(scope="module")
def agent2d(model2d):
    """The shipped policy's agent, noisy and lapsing, 20 trials: smooth controls, long trials."""
    actor, _, _ = load_ensemble_policy("firefly2d")
    theta = model2d.theta_space.default().unsqueeze(0)
    agent = motor_noise_policy(actor, model2d.action_spec, 0.3, lapse=0.1)
    return simulate_agents(model2d, agent, theta, 20, seed=0)[0]


def test_actions_logged_a_sample_late_are_named_so(tmp_path, model2d, agent2d):
    """Each row's action the one that set its own velocity (a logger's other convention) was
    refused as a unit, sign or world mistake."""
    columns = trials_to_columns(agent2d, model2d)
    for key in ("a_v", "a_w"):
        late = columns[key].astype(np.float64).copy()
        for label in np.unique(columns["trial"]):
            rows = np.flatnonzero(columns["trial"] == label)
            late[rows[1:]] = late[rows[:-1]]
        columns[key] = late
    _write_raw(columns, tmp_path / "late.csv")
    message = r"'w': follow the actions 0\.3\d*× .* the row after by 0\.9\d*×: each row holds"
    with pytest.raises(ValueError, match=message):
        read_trials(tmp_path / "late.csv", model2d)


def test_recordings_of_the_task_read_without_a_warning(tmp_path, model2d, trials2d, agent2d):
    """The new checks stay quiet on what the task makes: random controls, and the shipped
    policy's agent with motor noise and lapses."""
    for name, trials in (("random", trials2d), ("policy", agent2d)):
        path = write_trials(trials, tmp_path / f"{name}.csv", model2d)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert read_trials(path, model2d)["mask"].any()


@pytest.mark.parametrize("task", ["2d", "1d"])
def test_targets_in_another_unit_than_the_positions_are_refused(tmp_path, task, request):
    """Targets in cm beside positions in m passed (their unit is declared apart) and the fit
    put g_w on its bound, "identified"."""
    model = request.getfixturevalue(f"model{task}")
    columns = trials_to_columns(request.getfixturevalue(f"trials{task}"), model)
    _write_raw(columns, tmp_path / "m.csv")
    assert read_trials(tmp_path / "m.csv", model)["mask"].any()
    for name in model.target_names:
        columns[name] = columns[name].astype(np.float64) * 100
    _write_raw(columns, tmp_path / "cm.csv")
    names = "/".join(map(repr, model.target_names))
    with pytest.raises(ValueError, match=rf"field\(s\) {names}: [\d.]+ from the trial's first"):
        read_trials(tmp_path / "cm.csv", model)


def test_a_semicolon_export_and_a_time_in_ms_are_refused_saying_why(tmp_path, model2d, trials2d):
    """A semicolon CSV was "the file holds no samples", and a time in ms failed on the trial's
    length (18001 samples) with nothing pointing at the unit."""
    columns = trials_to_columns(trials2d, model2d)
    names = list(columns)
    lines = [";".join(names)]
    lines += [";".join(str(columns[n][i]) for n in names) for i in range(len(columns["time"]))]
    (tmp_path / "excel.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"is one column; expected comma-separated values"):
        read_trials(tmp_path / "excel.csv", model2d)
    columns["time"] = columns["time"].astype(np.float64) * 1000
    _write_raw(columns, tmp_path / "ms.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the resampling warning
        with pytest.raises(ValueError, match=r"a time in ms\? declare units\.time=ms"):
            read_trials(tmp_path / "ms.csv", model2d)


@pytest.mark.parametrize("rate_hz", [1000, 2000])
def test_a_time_in_ms_sampled_at_khz_is_refused_at_once_saying_why(
    tmp_path, model2d, trials2d, rate_hz
):
    """At 1 kHz a time in ms steps "1 s", ten of the task's: every trial was resampled (25001
    samples, 558 MB for a 10 MB file) after a warning, then refused with no word of the unit.
    Now its length is read first; a trial too long in seconds too gets no such hint."""
    row = {name: values[:1] for name, values in trials_to_columns(trials2d, model2d).items()}
    n = 2 * rate_hz + 1  # a trial of 2 s
    columns = {name: np.repeat(values, n) for name, values in row.items()}
    columns["time"] = np.arange(n) * 1000.0 / rate_hz
    _write_raw(columns, tmp_path / "khz.csv")
    message = (
        r"trial 0, field 'time': 20001 samples, each read as a model step; .* cut or drop "
        r"longer trials \(it lasts 2000 s: a time in ms\? declare units\.time=ms\)$"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused before resampling says a word
        with pytest.raises(ValueError, match=message):
            read_trials(tmp_path / "khz.csv", model2d)
    # too long in seconds: 7 s at this rate, or a 200 s block at the task's (not ms: the step
    # of a clock in ms read as s is longer than the task's)
    for name, duration, samples in (("long", 7.0, 71), ("block", 200.0, 2001)):
        columns["time"] = np.arange(n) * duration / (n - 1)
        _write_raw(columns, tmp_path / f"{name}.csv")
        with pytest.raises(ValueError, match=rf"{samples} samples, .* cut or drop longer trials$"):
            read_trials(tmp_path / f"{name}.csv", model2d)


def test_trials_going_on_past_the_stop_are_read_with_a_warning(tmp_path, model2d, trials2d):
    """A reward period exported with each trial (the agent standing still) was read without a
    word: on the audit's recording, a log-likelihood of −491 where the cut trials give −197."""
    columns = trials_to_columns(trials2d, model2d)
    plain = _write_recording(columns, tmp_path / "cut.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # trials cut at their stop: nothing to say
        read_trials(plain, model2d)
    rows = _rows(columns, 0)
    still = {name: np.repeat(values[rows[-1:]], 8) for name, values in columns.items()}
    still["time"] = still["time"] + model2d.dt * np.arange(1, 9)
    still["a_v"] = np.zeros(8)  # stopped, as at the stop itself
    longer = {n: np.concatenate([v[rows], still[n], v[rows[-1] + 1 :]]) for n, v in columns.items()}
    stop = columns["time"][rows[-1]]
    message = (
        rf"1 of {len(trials2d)} trials go on past the task's stop \(trial 0: 8 steps after its "
        rf"stop at {stop:g} s into it\), each scored as the agent's choice to go on: cut each"
    )
    with pytest.warns(UserWarning, match=message):
        read_trials(_write_recording(longer, tmp_path / "longer.csv"), model2d)


def test_a_chosen_stop_with_steps_after_it_is_refused_naming_the_file_and_trial(
    tmp_path, model1d, trials1d
):
    """A discrete task's stop ends its trial; the refusal named neither the file nor the
    recording's trial number ('trials: field 'action' stops at agent 0, trial 0, step 1')."""
    from irc_torchrl.envs.firefly1d import STOP

    columns = trials_to_columns(trials1d, model1d)
    columns["trial"] = columns["trial"] + 7  # the recording's own numbering
    rows = _rows(columns, 7)
    after = {name: values[rows[-1:]].repeat(2) for name, values in columns.items()}
    after["time"] = after["time"] + model1d.dt * np.arange(1, 3)
    longer = {n: np.concatenate([v[rows], after[n], v[rows[-1] + 1 :]]) for n, v in columns.items()}
    assert longer["action"][rows[-1]] == STOP  # the trial's own stop, then two more steps
    path = _write_recording(longer, tmp_path / "session.csv")
    stop = columns["time"][rows[-1]]
    message = (
        rf"^{path}: trial 7: field 'action' stops {stop:g} s into it, yet 2 steps follow; the "
        "task ends a trial at its stop, so cut the trial there$"
    )
    with pytest.raises(ValueError, match=message):
        read_trials(path, model1d)


def test_a_recording_that_hardly_moves_or_jitters_is_not_taken_for_a_unit_mistake(
    tmp_path, model2d, trials2d
):
    """The kinematic check regresses recorded steps on predicted ones: an agent standing
    still under tracker jitter, or a straight path whose heading carries float round-off,
    leaves the slope unsure and is read, where a ratio of path lengths refused it."""
    columns = trials_to_columns(trials2d, model2d)
    rng = np.random.default_rng(0)
    still = {k: v.astype(np.float64) for k, v in columns.items()}
    for name in ("v", "w", "a_v", "a_w"):
        still[name] = np.zeros_like(still[name])
    for name in ("x", "y"):  # the agent stands where it started; the tracker jitters by 1 mm
        first = {t: still[name][still["trial"] == t][0] for t in np.unique(still["trial"])}
        still[name] = np.array([first[t] for t in still["trial"]]) + 1e-3 * rng.standard_normal(
            len(still[name])
        )
    still["heading"] = np.zeros_like(still["heading"]) + 1e-7 * rng.standard_normal(
        len(still["heading"])
    )
    _write_raw(still, tmp_path / "still.npz")
    back = read_trials(tmp_path / "still.npz", model2d)
    assert torch.equal(back["mask"].sum(-1), trials2d["mask"].sum(-1))


def test_a_tasks_rate_limit_sets_the_speed_check(tmp_path, model2d, trials2d):
    """A task whose θ does not bound its speeds overrides ``rate_limit``: a lower one refuses
    the simulated recording's speeds naming it, ``None`` leaves speeds unchecked (a velocity in
    cm/s is then caught by the kinematic check alone)."""

    class Slow(Firefly2DModel):
        def rate_limit(self, unit: str) -> float | None:
            return 0.5 if unit == "distance/s" else super().rate_limit(unit)

    class Unchecked(Firefly2DModel):
        def rate_limit(self, unit: str) -> float | None:
            return None

    columns = trials_to_columns(trials2d, model2d)
    path, fast = tmp_path / "recording.csv", tmp_path / "fast.csv"
    _write_raw(columns, path)
    _write_raw(_scale(100.0, "v")(dict(columns)), fast)
    assert model2d.rate_limit("distance/s") == pytest.approx(16.0)
    assert read_trials(path, Unchecked())["state"].equal(read_trials(path, model2d)["state"])
    with pytest.raises(ValueError, match=r"below 0\.5 distance/s \(the task's rate_limit: "):
        read_trials(path, Slow())
    with pytest.raises(ValueError, match=r"field 'v': .* expected below 16 distance/s"):
        read_trials(fast, model2d)
    with pytest.raises(ValueError, match=r"'x'/'y': each step moves 0\.01× as far") as caught:
        read_trials(fast, Unchecked())
    assert "expected below" not in str(caught.value)


def test_a_written_recordings_times_are_its_steps_times_to_the_digit(tmp_path, trials2d, model2d):
    # 3 × 0.1 s was written 0.30000000000000004, which a lab's `time == 0.3` lookup misses
    write_trials(trials2d, tmp_path / "a.csv", model2d)
    with open(tmp_path / "a.csv") as f:
        times = [row["time"] for row in csv.DictReader(f)]
    assert len(times) > 10 and all(t == repr(round(float(t), 1)) for t in times)
