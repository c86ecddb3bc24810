"""Held trials: every malformed input is refused before any work, with a message naming it."""

import math

import pytest
import torch
from torchrl.data import Unbounded

from irc_torchrl.algorithms.simulate import first_trial_mask, simulate_agents
from irc_torchrl.data.files import atomic_path, staged, write_json
from irc_torchrl.data.trajectories import validate_trials
from irc_torchrl.envs import Firefly1DModel, Firefly2DModel, TaskEnv
from irc_torchrl.envs.model import action_in_spec


@pytest.fixture(scope="module")
def model():
    return Firefly1DModel()


@pytest.fixture(scope="module")
def trials(model):
    theta = model.theta_space.sample((2,), generator=torch.Generator().manual_seed(0))
    return simulate_agents(model, None, theta, 6, model.theta_space.default(), seed=0)


def test_valid_trials_pass_and_one_agent_gains_an_agent_dim(model, trials):
    assert validate_trials(trials, model).batch_size == trials.batch_size
    assert validate_trials(trials[0], model).batch_size == (1, *trials.shape[1:])


def test_first_trial_mask_keeps_steps_up_to_the_first_done():
    done = torch.tensor([[0, 0, 1, 0, 1], [1, 0, 0, 0, 0], [0, 0, 0, 0, 0]], dtype=torch.bool)
    expected = torch.tensor([[1, 1, 1, 0, 0], [1, 0, 0, 0, 0], [1, 1, 1, 1, 1]], dtype=torch.bool)
    assert torch.equal(first_trial_mask(done), expected)


def _nan_state(t):
    t["state"][1, 2, 0, 0] = float("nan")


def _inf_target(t):
    t["target"][0, 0, 0, 0] = float("inf")


def _bad_action(t):
    t["action"][0, 3, 0] = 3


def _negative_action(t):
    t["action"][1, 0, 0] = -1


def _mask_gap(t):
    t["mask"][0, 1, :] = False
    t["mask"][0, 1, 0] = True
    t["mask"][0, 1, 2] = True


def _empty_trial(t):
    t["mask"][1, 4, :] = False


def _theta_outside(t):
    t["task_theta"][0, 0, :, 0] = 9.0


def _task_theta_nan(t):
    t["task_theta"][1, 2, 0, 1] = float("nan")


@pytest.mark.parametrize(
    "corrupt, field",
    [
        (_nan_state, "'state' has NaN or inf at agent 1, trial 2, step 0"),
        (_inf_target, "'target' has NaN or inf at agent 0, trial 0, step 0"),
        (_bad_action, "'action' at agent 0, trial 3, step 0 is 3"),
        (_negative_action, "'action' at agent 1, trial 0, step 0 is -1"),
        (_mask_gap, "a gap ends at agent 0, trial 1, step 1"),
        (_empty_trial, "marks no step at agent 1, trial 4"),
        (_theta_outside, "'task_theta' at agent 0, trial 0, step 0: g_a=9 is outside its space"),
        (_task_theta_nan, "at agent 1, trial 2, step 0: log_sigma0=nan is outside its space"),
    ],
)
def test_malformed_values_name_the_field_and_place(model, trials, corrupt, field):
    bad = trials.clone()
    corrupt(bad)
    with pytest.raises((ValueError, TypeError), match=field.replace("(", r"\(")):
        validate_trials(bad, model)


def test_missing_field_lists_the_required_ones(model, trials):
    with pytest.raises(KeyError, match="missing field.*'mask'"):
        validate_trials(trials.exclude("mask"), model)


def test_wrong_shapes_and_dtypes(model, trials):
    with pytest.raises(ValueError, match="field 'state' expected shape"):
        validate_trials(trials.clone().set("state", trials["state"].repeat(1, 1, 1, 2)), model)
    with pytest.raises(TypeError, match="'mask' expected dtype bool"):
        validate_trials(trials.clone().set("mask", trials["mask"].float()), model)
    with pytest.raises(TypeError, match="'task_theta': expected a floating-point tensor"):
        validate_trials(trials.clone().set("task_theta", trials["task_theta"].long()), model)
    with pytest.raises(ValueError, match=r"batch dims \[n_agents, n_trials, T\]"):
        validate_trials(trials[0, 0], model)
    with pytest.raises(TypeError, match="expected a TensorDict"):
        validate_trials({"state": trials["state"]}, model)


def test_atomic_write_leaves_nothing_when_the_writer_fails(tmp_path):
    target = tmp_path / "summary.json"
    write_json(target, {"a": 1})
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert target.read_text() == '{\n  "a": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_staged_files_replace_their_namesakes_together_or_not_at_all(tmp_path):
    """A file or folder staged replaces its namesake (a folder over a folder, a file over a
    folder) only once the whole block has succeeded; a failure leaves the folder as it was."""
    (tmp_path / "a.csv").write_text("old a")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "part").write_text("old b")
    (tmp_path / "c").mkdir()
    (tmp_path / "keep.txt").write_text("mine")
    before = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    with pytest.raises(RuntimeError), staged(tmp_path) as staging:
        (staging / "a.csv").write_text("new a")
        raise RuntimeError("interrupted")
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == before
    assert (tmp_path / "a.csv").read_text() == "old a"
    with staged(tmp_path) as staging:
        (staging / "a.csv").write_text("new a")
        (staging / "b").mkdir()
        (staging / "b" / "other").write_text("new b")
        (staging / "c").write_text("a file now")
    assert (tmp_path / "a.csv").read_text() == "new a"
    assert [p.name for p in (tmp_path / "b").iterdir()] == ["other"]
    assert (tmp_path / "c").read_text() == "a file now"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b", "c", "keep.txt"]


def test_a_staged_summary_moves_in_last(tmp_path, monkeypatch):
    """The summary says a run finished: moved by name, a recovery's came before its trials/,
    so a stop between the two left a summary over the earlier run's trials."""
    from irc_torchrl.data import files

    moved, move = [], files._move

    def recorded(source, path):
        moved.append(path.name)
        move(source, path)

    monkeypatch.setattr(files, "_move", recorded)
    with staged(tmp_path) as staging:
        for name in ("summary.json", "trials", "a.png"):
            (staging / name).write_text(name)
    assert moved == ["a.png", "trials", "summary.json"]


def test_summaries_are_strict_json_with_null_for_numbers_that_are_not_finite(tmp_path):
    import json

    data = {"std": {"g_v": float("inf"), "sigma_v": 0.1}, "bounds": [float("nan"), (-1.0, 2)]}
    path = write_json(tmp_path / "summary.json", data)

    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    assert json.loads(path.read_text(), parse_constant=refuse) == {
        "std": {"g_v": None, "sigma_v": 0.1},
        "bounds": [None, [-1.0, 2]],
    }


def test_atomic_write_gives_the_usual_file_mode(tmp_path):
    import os

    umask = os.umask(0o022)
    try:
        path = write_json(tmp_path / "summary.json", {"a": 1})
    finally:
        os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o644


def test_a_trial_longer_than_the_task_allows_is_refused(model, trials):
    """Padding past ``max_steps`` is harmless; a recorded step there is not a trial the task
    (or the policy, which reads the step over ``max_steps``) could have produced."""
    longer = torch.cat([trials, trials[..., -5:]], -1)
    longer["mask"][..., model.max_steps :] = False
    assert validate_trials(longer, model).shape[-1] == model.max_steps + 5
    longer["mask"][0, 2, :] = True
    with pytest.raises(ValueError, match=f"agent 0, trial 2, step {model.max_steps}; the task"):
        validate_trials(longer, model)


def test_an_unbounded_action_spec_admits_every_finite_action():
    """A task whose controls have no bounds (an ``Unbounded`` spec, its box the dtype's
    extremes) steps with any finite action and its trials validate; NaN is still refused."""
    model = Firefly2DModel()
    model.action_spec = Unbounded(shape=(2,))
    action = torch.tensor([[5.0, 0.0], [-1e6, 0.3]])
    assert action_in_spec(model.action_spec, action).all()
    assert action_in_spec(model.action_spec, action, slack=1e-6).all()
    assert not action_in_spec(model.action_spec, torch.tensor([[math.nan, 0.0]])).any()
    env = TaskEnv(model, batch_size=(2,))
    env.step(env.reset().set("action", action))
    with pytest.raises(ValueError, match="finite"):
        env.step(env.reset().set("action", torch.tensor([[math.nan, 0.0], [0.0, 0.0]])))
    theta = model.theta_space.default().expand(2, -1)
    trials = simulate_agents(model, None, theta, 3, seed=0)
    assert validate_trials(trials, model).batch_size == trials.batch_size
