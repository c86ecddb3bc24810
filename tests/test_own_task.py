"""Algorithm 1 and 2 on a task of the user's own: the example's task trained, loaded, fitted and
recovered from Python and from the `irc` command line, and the refusals on the way."""

from __future__ import annotations

import copy
import json
import math
import re
import shutil
import statistics
from collections.abc import Callable

import numpy as np
import pytest
import torch
import yaml
from matplotlib.image import imread
from tensordict import TensorDict
from test_checkpoint import tiny
from test_examples import EXAMPLES, _load_example
from torchrl.data import Bounded, OneHot, TensorSpec, Unbounded

from irc_torchrl.algorithms.ensemble import (
    EvaluationConfig,
    Firefly2DConfig,
    load_ensemble_critic,
    load_ensemble_policy,
    train_ensemble,
)
from irc_torchrl.algorithms.fit import fit_theta
from irc_torchrl.algorithms.recover2d import predicted_widths
from irc_torchrl.checkpoint import load_checkpoint
from irc_torchrl.cli import main
from irc_torchrl.envs import check_model
from irc_torchrl.envs.firefly1d import Firefly1DModel
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.modules.actor_critic import make_actor
from irc_torchrl.objectives.inverse import InverseRationalLoss


@pytest.fixture(scope="module")
def reach():
    return _load_example("define_your_task")


def _own(reach) -> Firefly2DConfig:
    """The example's settings for a short run (one thread, about 15 s): 40k frames at a faster
    actor learning rate, a smaller evaluation grid, a checkpoint every 250 updates."""
    config = reach.ensemble_config(40_960, seed=0)
    config.ddpg.lr_actor = 1e-3
    config.evaluation = EvaluationConfig(n_theta=8, trials_per_theta=4, every=250)
    config.checkpoint_every = 250
    return config


@pytest.fixture(scope="module")
def own_task(reach, tmp_path_factory):
    out = tmp_path_factory.mktemp("own_task")
    return train_ensemble(_own(reach), out=out, progress=False, model=reach.ReachModel()), out


def test_an_own_task_trains_towards_its_optimal_controller(reach, own_task):
    """Algorithm 1 learns the example's task from a random warm-up: on 16 θ of the prior the
    kept actor's cost is on average within 3× the LQG controller's (measured 1.59×; 1.23× after
    the example's 200k frames), against over 20× (measured 104×) for the same actor untrained."""
    result, _ = own_task
    model = result.model
    trained = reach.compare_with_controller(model, result.actor, seed=0)
    torch.manual_seed(0)
    untrained = make_actor(model, result.config.ddpg.hidden, result.config.ddpg.activation)
    first = reach.compare_with_controller(model, untrained, seed=0)
    assert statistics.mean(trained["cost_ratio"]) < 3
    assert statistics.mean(first["cost_ratio"]) > 20
    assert trained["mean_cost"]["controller"] == first["mean_cost"]["controller"]  # same trials


def test_agents_acting_by_an_own_tasks_learned_policy_are_fitted_with_it(
    reach, own_task, monkeypatch
):
    """Algorithm 2 with the learned policy of the user's task (the example's three agents, 20
    trials each, seed 0): marginal's likelihood at θ* is a particle filter's (250 particles
    here, the example's 1000 take 4× as long) to 2 nats per agent (measured within 0.8; 0.4
    with 1000), map's at least 10 below (measured 24-35), and marginal recovers the
    observation noises within 0.02 (measured within 0.01) and the motor noise within 0.015
    (measured within 0.004), which map inflates."""
    monkeypatch.setattr(reach, "PARTICLES", 250)
    result, _ = own_task
    fits = reach.fit_learned(result.model, result.actor, 20, seed=0)
    marginal, map_ = fits["marginal"], fits["map"]
    assert all(abs(gap) < 2 for gap in marginal["gap_at_truth"])
    assert all(gap < -10 for gap in map_["gap_at_truth"])
    for truth, agent in zip(reach.TRUE_THETA, marginal["agents"], strict=True):
        assert abs(agent["theta_hat"]["obs_sigma"] - truth["obs_sigma"]) < 0.02
    assert all(abs(noise - reach.MOTOR_NOISE) < 0.015 for noise in marginal["motor_noise"])
    assert all(m > n for m, n in zip(map_["motor_noise"], marginal["motor_noise"], strict=True))


def test_an_own_tasks_checkpoint_carries_its_name_and_loads_only_with_its_model(reach, own_task):
    """The checkpoint, summary and config name the model's task; the kept actor reloads with
    the model, and neither the firefly loader nor a model of another θ space takes it."""
    result, out = own_task
    path = out / "checkpoint.pt"
    assert load_checkpoint(path)["task"] == "reach_and_hold" == result.config.task
    summary = json.loads((out / "summary.json").read_text())
    assert summary["task"] == "reach_and_hold"
    assert set(summary["theta_sensitivity"]) == {"g", "obs_sigma", "effort_cost"}
    assert "stop_sharpness" not in summary  # the firefly's forward control has no meaning here
    assert yaml.safe_load((out / "config.yaml").read_text())["task"] == "reach_and_hold"
    actor, model, _ = load_ensemble_policy(path, model=result.model)
    for name, value in result.actor.state_dict().items():
        assert torch.equal(actor.state_dict()[name], value)
    critic, _, _ = load_ensemble_critic(path, model=result.model)
    assert critic(result.actor(_reach_beliefs(model)))["state_action_value"].shape == (3, 1)
    with pytest.raises(ValueError, match="task is 'reach_and_hold', expected 'firefly2d'"):
        load_ensemble_policy(path)

    class Narrower(reach.ReachModel):
        theta_space = reach.reach_theta_space().fix(effort_cost=0.1)

    with pytest.raises(
        ValueError,
        match=r"theta_space does not match the model's θ space \(fixed \{'sigma_v': 0\.05\} "
        r"against \{'effort_cost': 0\.1, 'sigma_v': 0\.05\}, the checkpoint's first\)$",
    ):
        load_ensemble_policy(path, model=Narrower())

    class Wider(reach.ReachModel):
        theta_space = reach.reach_theta_space().with_range("g", 0.5, 3.0)

    with pytest.raises(ValueError, match=r"\(g: high 2\.0 against 3\.0, the checkpoint's first\)$"):
        load_ensemble_policy(path, model=Wider())


def _reach_beliefs(model) -> TensorDict:
    """Three agents' beliefs at the start of a trial of the reach task."""
    state = torch.zeros(3, 2)
    target = torch.tensor([[-0.5], [0.2], [0.9]])
    theta = model.theta_space.default().expand(3, -1)
    mean, cov = model.initial_belief(state, target, theta)
    step = torch.zeros(3, 1, dtype=torch.int64)
    return TensorDict(
        {"belief": {"mean": mean, "cov": cov}, "target": target, "step": step, "theta": theta},
        batch_size=[3],
    )


def test_an_own_task_without_success_is_evaluated_and_logged_by_its_return(own_task):
    """The task defines no success: every evaluation has its return and no success rate, and
    the CSV logger writes the return but no success rate."""
    result, out = own_task
    assert result.history and all(row["success_rate"] is None for row in result.history)
    assert all(math.isfinite(row["mean_return"]) for row in result.history)
    assert result.best["per_theta_success"] is None
    assert len(result.best["per_theta_return"]) == result.config.evaluation.n_theta
    logged = {p.stem for p in out.glob("logs/*/scalars/*.csv")}
    assert "mean_return" in logged and "success_rate" not in logged


def test_an_own_task_resumes_from_its_checkpoint(own_task):
    """Resumed with its model, a run continues the checkpoint's counters (and refuses the
    firefly task's model)."""
    result, out = own_task
    longer = copy.deepcopy(result.config)
    longer.ddpg.total_frames += 4096  # the buffer refills with 2048 frames before updating
    resumed = train_ensemble(
        longer, resume=out / "checkpoint.pt", progress=False, model=result.model
    )
    assert resumed.frames == result.frames + 4096 and resumed.updates > result.updates
    assert resumed.history[: len(result.history)] == result.history  # the checkpoint's
    updates = [row["updates"] for row in resumed.history]
    assert updates == sorted(set(updates))  # counted on from the checkpoint's
    with pytest.raises(ValueError, match="task is 'reach_and_hold', expected 'firefly2d'"):
        train_ensemble(tiny(), resume=out / "checkpoint.pt", progress=False)


def test_the_firefly_task_given_as_a_model_trains_and_loads_as_by_default(tmp_path):
    """``model=Firefly2DModel()`` is the default task: the same training bit for bit (the
    pursuit warm-up included) and the shipped checkpoint's policy."""
    default = train_ensemble(tiny(), progress=False)
    given = train_ensemble(tiny(), progress=False, model=Firefly2DModel())
    for name, value in default.actor.state_dict().items():
        assert torch.equal(given.actor.state_dict()[name], value)
    assert given.history[-1]["mean_return"] == default.history[-1]["mean_return"]
    shipped, _, _ = load_ensemble_policy()
    loaded, _, _ = load_ensemble_policy("firefly2d", model=Firefly2DModel())
    for name, value in shipped.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value)


def test_the_progress_bar_shows_the_success_rate_or_for_a_task_without_one_the_return(
    reach, monkeypatch
):
    from irc_torchrl.algorithms import ensemble

    shown = []

    class Bar:
        def update(self, n: int) -> None:
            pass

        def set_postfix(self, **values: str) -> None:
            shown.append(values)

        def close(self) -> None:
            pass

    monkeypatch.setattr(ensemble, "_progress_bar", lambda *args: Bar())
    train_ensemble(tiny("evaluation.every=1000"), progress=True)
    assert set(shown[-1]) == {"success", "best"} and shown[-1]["success"].endswith("%")
    config = reach.ensemble_config(1536, seed=0)
    config.ddpg.warmup_frames, config.logger = 1024, "none"
    result = train_ensemble(config, progress=True, model=reach.ReachModel())
    assert shown[-1] == {
        "ret": f"{result.history[-1]['mean_return']:.3g}",
        "best": f"{result.best['mean_return']:.3g}",
    }


def test_a_task_is_named_by_its_class_unless_it_or_a_base_names_it(reach):
    """The checkpoints' task name: a class attribute, inherited, or the class's own name; an
    instance may set its own."""

    class Narrower(reach.ReachModel):
        pass

    class Unnamed(TaskModel):  # abstract: its name is read off the class
        pass

    class Below(Unnamed):
        pass

    class Mine(reach.ReachModel):
        def __init__(self) -> None:
            self.name = "mine"

    assert Firefly2DModel().name == "firefly2d" and Firefly1DModel().name == "firefly1d"
    assert Narrower().name == "reach_and_hold"
    assert Unnamed.name == "Unnamed" and Below.name == "Below"  # a name given, not taken
    assert Mine().name == "mine" and Mine.name == "reach_and_hold"


def test_a_model_on_another_device_than_the_configs_trains_on_a_copy_moved_there():
    """Its action spec (the actor's and the noise's bounds) moves; the model given stays."""
    from irc_torchrl.algorithms.ensemble import _on_device

    model = Firefly2DModel()
    assert _on_device(model, torch.device("cpu")) is model
    moved = _on_device(model, torch.device("meta"))
    assert moved.action_spec.device == torch.device("meta") and moved.name == "firefly2d"
    assert model.action_spec.device == torch.device("cpu")


def _with_actions(spec: TensorSpec) -> Callable[[], Firefly2DModel]:
    """The 2D task with another action spec."""

    def build() -> Firefly2DModel:
        model = Firefly2DModel()
        model.action_spec = spec
        return model

    return build


@pytest.mark.parametrize(
    "change, model, message",
    [
        ({"warmup_policy": "pursuit"}, "reach", "ddpg.warmup_policy='pursuit' runs the firefly2d"),
        (
            {"theta_fixed": {"g": 1.0}},
            "reach",
            "theta_fixed builds the firefly2d task's θ space; for a model given, fix them",
        ),
        ({}, Firefly1DModel, "model.action_spec: expected a bounded box of continuous"),
        (
            {},
            _with_actions(Unbounded(shape=(2,), dtype=torch.float32)),
            "model.action_spec: expected a bounded box of continuous actions, shape",
        ),
        (
            {},
            _with_actions(Bounded(0, 2, shape=(2,), dtype=torch.int64)),
            "model.action_spec: expected a bounded box of continuous actions, shape",
        ),
        ({}, _with_actions(OneHot(3)), "got OneHot of torch.bool, shape \\[3\\]"),
        ({}, lambda: "not a model", "model: expected a TaskModel, got str"),
        (
            {},
            "succeeded [B]",
            r"model.succeeded: expected None or bool \[2, 1\], as model.stops gives, got "
            r"torch.bool \[2\]",
        ),
        ({}, lambda: Firefly2DModel, r"model: got the class Firefly2DModel; pass an instance"),
    ],
)
def test_an_own_task_the_trainer_cannot_train_is_refused_before_any_work(
    reach, change, model, message, monkeypatch
):
    from irc_torchrl.algorithms import ensemble

    monkeypatch.setattr(ensemble, "_train", lambda *a: pytest.fail("trained"))
    config = reach.ensemble_config(1024, seed=0)
    config.theta_fixed = change.get("theta_fixed", {})
    config.ddpg.warmup_policy = change.get("warmup_policy", "random")
    if model == "succeeded [B]":

        class Flat(reach.ReachModel):
            def succeeded(self, state, target, stop, theta):
                return stop.squeeze(-1)

        model = Flat
    model = reach.ReachModel() if model == "reach" else model()
    with pytest.raises(ValueError, match=message):
        train_ensemble(config, progress=False, model=model)


#: the example's task as ``irc train --model`` names it, and a short run's settings
REACH = f"{EXAMPLES / 'define_your_task.py'}:ReachModel"
#: (the default for a task other than the firefly warms up with random actions)
SHORT = [
    "ddpg.warmup_frames=1024",
    *("ddpg.n_envs=32", "evaluation.n_theta=4", "evaluation.trials_per_theta=2"),
    *("evaluation.every=20", "logger=none"),
]


def test_irc_train_trains_and_resumes_a_task_named_on_the_command_line(tmp_path, capsys):
    """``irc train --model FILE.py:Class`` trains the user's task (no success: the return
    alone is printed) and resumes it from its checkpoint."""
    out = tmp_path / "run"
    argv = ["train", "--model", REACH, "--quiet", *SHORT]
    assert main([*argv, "--out", str(out), "ddpg.total_frames=2048"]) == 0
    printed = capsys.readouterr().out
    assert "best policy: return " in printed and "success" not in printed
    first = load_checkpoint(out / "checkpoint.pt")
    assert first["task"] == first["config"]["task"] == "reach_and_hold"
    more = ["--resume", str(out / "checkpoint.pt"), "--out", str(tmp_path / "more")]
    assert main([*argv, *more, "ddpg.total_frames=4096"]) == 0
    resumed = load_checkpoint(tmp_path / "more" / "checkpoint.pt")["counters"]
    assert resumed["updates"] > first["counters"]["updates"]


@pytest.mark.parametrize(
    "model, extra, message",
    [
        ("bad", [], "--model: expected FILE.py:Class or module:Class, got 'bad'"),
        ("nosuch.py:Task", [], "--model: no file at nosuch.py"),
        (
            REACH[:-10] + "LQGController",
            [],
            r"to be a TaskModel subclass, got class LQGController \(bases: Module\)",
        ),
        (REACH[:-10] + "Nope", [], "to be a TaskModel subclass, got nothing by that name"),
        (
            "irc_torchrl.envs.firefly1d:Firefly1DModel",
            [],
            r"--model: Firefly1DModel's actions are Categorical \[\]; expected continuous actions",
        ),
        (
            REACH,
            ["task=firefly2d"],
            "config: task must be the model's, 'reach_and_hold', got 'firefly2d'",
        ),
        (REACH, ["ddpg.collector_workers=2"], "--model: a task from a file .* cannot be sent"),
    ],
)
def test_irc_train_refuses_a_model_it_cannot_train_before_any_work(
    model, extra, message, tmp_path, capsys
):
    out = tmp_path / "run"
    argv = ["train", "--model", model, "--out", str(out), "--quiet", *SHORT, *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert not out.exists()


def test_a_task_file_imports_the_modules_beside_it(tmp_path, capsys):
    """A task file that imports a module of its own folder failed (`No module named ...`) where
    `python FILE.py` would run: the file's folder is searched as Python's script folder is."""
    shutil.copy(EXAMPLES / "define_your_task.py", tmp_path / "lab_tasks.py")
    (tmp_path / "my_task.py").write_text("from lab_tasks import ReachModel  # noqa: F401\n")
    argv = ["train", "--model", f"{tmp_path / 'my_task.py'}:ReachModel", "--quiet", *SHORT]
    assert main([*argv, "--out", str(tmp_path / "run"), "task=firefly2d"]) == 2
    err = capsys.readouterr().err  # refused past the import, for the setting
    assert "config: task must be the model's, 'reach_and_hold', got 'firefly2d'" in err, err


def test_irc_simulate_and_fit_take_a_task_named_on_the_command_line(own_task, tmp_path, capsys):
    """``irc simulate`` and ``irc fit`` with ``--model`` and the task's checkpoint: recordings
    in the task's own columns, and θ̂ from them (2 agents × 20 trials at one θ*; tolerances:
    the observation noise within 0.03, the motor noise within 0.02);
    the belief figures over time only, the overhead view needing a position in the plane."""
    _, out = own_task
    common = ["--model", REACH, "--checkpoint", str(out / "checkpoint.pt"), "--quiet"]
    truth = {"g": 1.3, "obs_sigma": 0.1, "effort_cost": 0.2}
    settings = [f"theta.{name}={value}" for name, value in truth.items()]
    recorded = tmp_path / "recorded"
    argv = ["simulate", *common, "--out", str(recorded), "n_agents=2", "n_trials=20", *settings]
    assert main(argv) == 0
    assert json.loads((recorded / "summary.json").read_text())["task"] == "reach_and_hold"
    files = [str(recorded / f"agent{i}.csv") for i in range(2)]
    assert open(files[0]).readline().startswith("trial,time,x,v,a,target_x,theta.g,")
    fitted = tmp_path / "fitted"
    assert main(["fit", *files, *common, "--out", str(fitted)]) == 0
    summary = json.loads((fitted / "summary.json").read_text())
    assert summary["task"] == "reach_and_hold"
    for agent in summary["agents"]:
        assert agent["theta_true"] == pytest.approx({**truth, "sigma_v": 0.05})
        assert abs(agent["theta_hat"]["obs_sigma"] - truth["obs_sigma"]) < 0.03
        assert abs(agent["motor_noise"][0] - 0.1) < 0.02
    figures = {path.name for path in fitted.glob("*.png")}
    assert {"agent0_beliefs_time.png", "agent1_beliefs_time.png"} <= figures
    assert not any("overhead" in name for name in figures)
    capsys.readouterr()
    # the packaged checkpoint is the firefly's, and a task from a file stays in this process
    argv = ["fit", *files, "--model", REACH, "--out", str(tmp_path / "none"), "--quiet"]
    assert main(argv) == 2
    assert "learned for 'reach_and_hold' (a file), got the packaged" in capsys.readouterr().err
    assert main([*argv, "--checkpoint", str(out / "checkpoint.pt"), "workers=2"]) == 2
    assert "--model: a task from a file" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


#: a task file as users write them (a dataclass under postponed annotations, which looks its
#: module up by name), with a task needing an argument and an abstract one
TASK_FILE = """
from __future__ import annotations

import dataclasses

from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import TaskModel


@dataclasses.dataclass
class Settings:
    reward: float = 5.0


class Task(Firefly2DModel):
    name = "from_file"

    def __init__(self) -> None:
        super().__init__(reward_value=Settings().reward)


class Sized(Firefly2DModel):
    def __init__(self, size: float) -> None:
        super().__init__()


class Partial(TaskModel):
    pass
"""


def test_a_task_file_is_imported_as_a_module_of_its_own(tmp_path):
    from irc_torchrl.cli import _task_model

    (tmp_path / "my_task.py").write_text(TASK_FILE)
    model = _task_model(f"{tmp_path / 'my_task.py'}:Task")
    assert (model.name, model.reward_value) == ("from_file", 5.0)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("my_task.py:Sized", r"--model: Sized\(\) must build without arguments"),
        ("my_task.py:Partial", "--model: Partial is abstract; expected it to define"),
        ("no_such_module:Task", "--model: cannot import no_such_module .*expected a file or an"),
        ("bad.py:Task", "--model: cannot import bad.py .*invalid syntax"),
    ],
)
def test_a_task_that_cannot_be_built_is_refused_naming_the_option(
    spec, message, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my_task.py").write_text(TASK_FILE)
    (tmp_path / "bad.py").write_text("class Task(:\n")
    assert main(["train", "--model", spec, "--out", "run", "--quiet"]) == 2
    assert re.search(message, capsys.readouterr().err)
    assert not (tmp_path / "run").exists()


# --- the recovery experiment on a task of the user's own -----------------------------------

#: ``irc recover``'s agents made few and short (3 agents × 20 trials, one thread), each fitted
#: from the best of 8 screened draws
SMALL_RECOVERY = ["n_prior_agents=2", "n_mistaken_agents=1", "n_trials=20", "threads=1",
                  "fit.n_screen=8", "fit.n_starts=1"]  # fmt: skip


@pytest.fixture(scope="module")
def own_recovery(own_task, tmp_path_factory):
    """``irc recover --model`` on the example's task with its short run's policy, calibrated by
    one simulated dataset per agent (about 50 s)."""
    _, trained = own_task
    out = tmp_path_factory.mktemp("own_recovery")
    argv = ["recover", "--model", REACH, "--checkpoint", str(trained / "checkpoint.pt")]
    assert main([*argv, "--out", str(out), "--quiet", *SMALL_RECOVERY, "calibrate=1"]) == 0
    return json.loads((out / "summary.json").read_text()), out


def test_irc_recover_runs_the_recovery_experiment_on_a_task_named_on_the_command_line(
    reach, own_recovery
):
    """Two agents in their own worlds and one mistaken agent in the θ space's defaults,
    simulated with the learned policy and fitted by both estimators (20 trials each): the
    summary carries the task's θ units and state; marginal's intervals hold the agents' θ*
    but beside a bound (measured 7 of 9: agent 0 trades its gain against an effort cost
    fitted 0.021 [0.020, 0.031] beside the bound 0.02 for 0.083, g 1.59 [1.53, 1.65] for 1.24,
    intervals from the curvature too narrow on that ridge, README; 9 of 9 on the data another
    seed simulated), its observation noises
    lie within 0.04 (measured 0.031; 0.025) and its motor noise within 0.01 (measured 0.0998
    for 0.1; map's 0.114), and it recovers the agents' own belief errors (the part of the
    belief the states do not reveal) in position at r ≥ 0.9 (measured 0.932; 0.942), where
    map, blind to the agents' observation noise, stays below 0.5 (0.289; 0.176), and in
    velocity at r ≥ 0.8 (0.861); the calibration's intervals hold each θ̂."""
    summary, _ = own_recovery
    assert summary["task"] == "reach_and_hold"
    assert summary["mistaken"] == [False, False, True]
    assert (summary["state_names"], summary["state_units"]) == (["x", "v"], list(STATE_UNITS))
    assert summary["units"] == reach.reach_theta_space().units
    marginal, map_ = summary["methods"]["marginal"], summary["methods"]["map"]
    free = ("g", "obs_sigma", "effort_cost")
    bounds = {p.name: (p.low, p.high) for p in reach.reach_theta_space().parameters}
    missed = []
    for agent in marginal["agents"]:
        theta_hat = agent["theta_hat"]
        beside = any(
            min(abs(theta_hat[n] - b) for b in bounds[n]) < 0.02 * (bounds[n][1] - bounds[n][0])
            for n in free
        )
        for name in free:
            truth = agent["theta_true"][name]
            covered = agent["ci_low"][name] <= truth <= agent["ci_high"][name]
            assert covered or beside, (name, agent)
            missed += [] if covered else [name]
        assert abs(theta_hat["obs_sigma"] - agent["theta_true"]["obs_sigma"]) < 0.04
    assert missed in ([], ["g", "effort_cost"])
    assert abs(marginal["motor_noise_hat"] - 0.1) < 0.01 < map_["motor_noise_hat"] - 0.1
    beliefs = marginal["beliefs"]
    assert beliefs["belief_error_correlation"] == beliefs["belief_error_by_component"]["x"]
    assert beliefs["belief_error_correlation"] >= 0.9
    assert map_["beliefs"]["belief_error_correlation"] < 0.5
    assert beliefs["belief_error_by_component"]["v"] >= 0.8
    calibrated = marginal["calibrated"]
    assert set(calibrated["parameters"]) == set(free)
    for agent, fitted in zip(calibrated["agents"], marginal["agents"], strict=True):
        for name in free:
            theta_hat = fitted["theta_hat"][name]
            assert agent["ci_low"][name] <= theta_hat <= agent["ci_high"][name], (name, agent)


#: the example task's state units (x, v)
STATE_UNITS = ("distance", "distance/s")


def test_an_own_tasks_recovery_draws_its_beliefs_over_time_and_report_redraws_them(
    own_recovery, tmp_path
):
    """One-dimensional positions have no overhead view; ``irc report`` redraws every figure
    pixel for pixel from the folder alone (the summary names the state and its units)."""
    summary, out = own_recovery
    figures = sorted(path.name for path in out.glob("*.png"))
    methods = ("map", "marginal")
    kinds = ("beliefs_time", "recovery")
    assert figures == sorted(f"{kind}_{m}.png" for kind in kinds for m in methods)
    copy_of = tmp_path / "copy"
    shutil.copytree(out, copy_of)
    for png in copy_of.glob("*.png"):
        png.unlink()
    assert main(["report", str(copy_of)]) == 0
    for name in figures:
        assert np.array_equal(imread(copy_of / name), imread(out / name)), name


@pytest.mark.parametrize(
    "extra, message",
    [
        ([], "--checkpoint: expected the policy `irc train --model` learned for 'reach_and_hold'"),
        (
            ["task=firefly2d", "CHECKPOINT"],
            "config: task must be the model's, 'reach_and_hold', got 'firefly2d'",
        ),
        (["fit.workers=2", "CHECKPOINT"], "--model: a task from a file .* cannot be sent"),
        (["--checkpoint", "a.pt", "CHECKPOINT"], "checkpoint: given twice"),
    ],
)
def test_irc_recover_refuses_an_own_task_it_cannot_run_before_any_work(
    own_task, extra, message, tmp_path, capsys
):
    """The packaged checkpoint is the firefly's, a config naming another task is refused, a
    task from a file stays in this process, and the checkpoint is given once."""
    _, trained = own_task
    checkpoint = f"checkpoint={trained / 'checkpoint.pt'}"
    extra = [checkpoint if item == "CHECKPOINT" else item for item in extra]
    out = tmp_path / "run"
    argv = ["recover", "--model", REACH, "--out", str(out), "--quiet", *SMALL_RECOVERY, *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert not out.exists()


@pytest.mark.parametrize("command", [["simulate"], ["fit", "a.csv"]])
def test_a_policy_of_another_task_is_refused_naming_the_option_that_mends_it(
    own_task, command, tmp_path, capsys
):
    """``--model`` with the packaged firefly policy, or a task's own policy without
    ``--model``: one line saying which option to give, before any work."""
    _, trained = own_task
    out = tmp_path / "run"
    for extra, message in (
        (["--model", REACH], "--checkpoint: expected the policy `irc train --model` learned "
         "for 'reach_and_hold' (a file), got the packaged firefly2d"),
        (["--checkpoint", str(trained / "checkpoint.pt")], "holds a policy for 'reach_and_hold'; "
         "expected --model naming that task (FILE.py:Class or module:Class)"),
    ):  # fmt: skip
        assert main([*command, *extra, "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"irc {command[0]}: error: ") and message in err, err
        assert not out.exists()


def test_an_own_tasks_recovery_config_without_its_model_is_refused_naming_the_option(
    own_recovery, tmp_path, capsys
):
    """Rerunning a recovery of an own task from its config.yaml needs the task again."""
    _, out = own_recovery
    argv = ["recover", "--config", str(out / "config.yaml"), "--out", str(tmp_path / "run")]
    assert main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "task must be 'firefly2d' (a task of your own is given as a model, --model)" in err
    assert not (tmp_path / "run").exists()


def test_predicted_widths_narrow_with_the_trials_of_an_own_task(reach, own_task):
    """The Fisher information's prediction before any fit, on the user's task: the gain's and
    the observation noise's intervals narrow with four times the trials (by about half, as
    1/√n says: measured 0.41 and 0.46)."""
    result, _ = own_task
    widths = predicted_widths(result.model, result.actor, n_trials=(10, 40), n_agents=3)
    for name in ("g", "obs_sigma"):
        assert 0.3 < widths[40][name] / widths[10][name] < 0.7, (name, widths)


# --- the probe of a task's methods ------------------------------------------------------------
def _faulty(reach, **methods):
    """The example's task with ``methods`` replaced (each a function of the model's self)."""
    return type("Faulty", (reach.ReachModel,), {"name": "faulty", **methods})()


def _detached(self, state, action, theta):
    return type(self).__mro__[1].transition(self, state, action, theta.detach())


def _branching(self, state, action, theta):  # a Python branch on a tensor's value
    x, v = state[..., :1], state[..., 1:]
    v = v + self.parameter(theta, "g") * action * self.dt if float(v.sum()) >= 0 else v
    return torch.cat([x + v * self.dt, v], -1)


@pytest.mark.parametrize(
    "methods, message",
    [
        ({"observe": TaskModel.observe, "observation_cov": TaskModel.observation_cov},
         r"model\.observe: expected \[\*B, 1\] \(\[2, 1\] for inputs of batch \[2\]\), got "
         r"\[2, 0\] \(a task with observations, observation_dim > 0, overrides observe"),
        ({"process_cov": lambda self, s, a, th: torch.ones(*s.shape[:-1], 1, 1) * 1e-4},
         r"model\.process_cov: expected \[\*B, 2, 2\] \(\[2, 2, 2\] .*got \[2, 1, 1\]"),
        ({"process_cov": lambda self, s, a, th: torch.tensor([[1.0, 0.5], [0.0, 1.0]]).expand(
            *s.shape[:-1], 2, 2)},
         r"model\.process_cov: expected a symmetric covariance"),
        ({"observation_cov": lambda self, s, th: -torch.ones(*s.shape[:-1], 1, 1)},
         r"model\.observation_cov: expected a positive semi-definite covariance"),
        ({"transition": lambda self, s, a, th: s[..., 0]},
         r"model\.transition: expected \[\*B, 2\] .*got \[2\]$"),
        ({"transition": lambda self, s, a, th: s.double()},
         r"model\.transition: expected torch\.float32 \(the dtype of initial_state's state\), "
         r"got torch\.float64"),
        ({"transition": _detached},
         r"model\.transition: its output moves with θ parameter 'g' \(a finite difference\) "
         r"but carries no gradient to it \(autograd\); expected every method differentiable"),
        ({"transition": _branching},
         r"model\.transition_jacobian: failed on CPU inputs .* override it with an analytic "
         r"Jacobian$"),
        ({"stops": lambda self, a, step: torch.zeros_like(step, dtype=torch.float32)},
         r"model\.stops: expected torch\.bool"),
        ({"initial_state": lambda self, th, g: torch.zeros(*th.shape[:-1], 2)},
         r"model\.initial_state: expected a pair of tensors \[\[2, 2\], \[2, 1\]\] .*got "
         r"\[2, 2\]$"),
        ({"belief_reward": lambda self, m, c, t, a, s, th: (m[..., :1] - 2).log()},
         r"model\.belief_reward: NaN or inf at the default θ \(g=1, sigma_v=0\.05, "
         r"obs_sigma=0\.05, effort_cost=0\.1\); expected finite values"),
        ({"belief_feature_dim": 6},
         r"model\.belief_features: expected \[\*B, 10\] .*got \[2, 9\]$"),
    ],
)  # fmt: skip
def test_a_task_whose_methods_return_the_wrong_thing_is_refused_naming_the_method(
    reach, methods, message
):
    """A task's own methods were called deep inside rollouts and fits: a missing observe ran
    with no observation, a [*B, 1, 1] covariance broadcast the same noise into both states, a
    θ detached fitted "not identified", and other faults came out as torch's errors naming
    neither the method nor the form. The env and the inverse (both estimators) probe them."""
    model = _faulty(reach, **methods)
    with pytest.raises(ValueError, match=message):
        TaskEnv(model, batch_size=(3,))
    for method in ("map", "marginal"):
        with pytest.raises(ValueError, match=message):
            InverseRationalLoss(model, reach.controller_action_model(model), method=method)


def test_nan_from_a_tasks_dynamics_at_a_theta_off_the_default_names_the_method(reach):
    """NaN states (here sqrt(g - 0.8), NaN for g < 0.8, inside the prior) were blamed on the
    action two steps later ('action: expected finite values'); the step names the method
    and the world's θ, and other θ step on."""

    def transition(self, state, action, theta):
        root = (self.parameter(theta, "g") - 0.8).sqrt()
        return reach.ReachModel.transition(self, state, action, theta * root / root)

    model = _faulty(reach, transition=transition)
    space = model.theta_space
    theta = torch.stack([space.from_dict({"g": g}) for g in (1.2, 0.6)])
    env = TaskEnv(model, batch_size=(2,), theta=theta, seed=0)
    td = env.reset()
    td["action"] = torch.full((2, 1), 0.5)
    with pytest.raises(
        ValueError,
        match=r"^model\.transition \(with process_cov's noise\): NaN or inf at the world's θ "
        r"\(g=0\.6, sigma_v=0\.05, obs_sigma=0\.05, effort_cost=0\.1\); expected finite values",
    ):
        env.step(td)
    fine = TaskEnv(model, batch_size=(1,), theta=theta[:1], seed=0).rollout(5)
    assert torch.isfinite(fine["next", "state"]).all()


def test_a_fit_skips_the_screened_theta_where_a_task_gives_nan(reach):
    """A task NaN in part of its prior (sqrt(g - 0.7), g in [0.5, 2]): the screen ranked the
    NaN draws first (topk sorts NaN above every number) and the fit died in linalg (map) or
    in the outer filter's Cholesky (marginal); those draws are named and not started from."""

    def transition(self, state, action, theta):
        root = (self.parameter(theta, "g") - 0.7).sqrt()
        return reach.ReachModel.transition(self, state, action, theta * root / root)

    model = _faulty(reach, transition=transition)
    theta, trials = reach.simulate(model, reach.controller_policy(model), 5, seed=0)
    held = trials[:1]
    for method in ("map", "marginal"):
        loss = InverseRationalLoss(model, reach.controller_action_model(model), method=method)
        with pytest.warns(UserWarning, match=r"fit: the log-likelihood is NaN at \d+ of 16 "):
            result = fit_theta(loss, held, n_starts=1, n_screen=16, max_iter=3, seed=0)
        assert torch.isfinite(result.theta_hat).all() and result.theta_hat[0, 0] > 0.7, method
        assert torch.isfinite(result.log_likelihood).all(), method


@pytest.mark.parametrize(
    "variant",
    ["float64", "unbounded actions", "no observation", "a noise at 0", "no gradients"],
)
def test_the_probe_accepts_legitimate_variants_of_a_task(reach, variant):
    """The probe refuses no task the env and the inverse run: one computing in float64, with
    unbounded actions, without observations, with a σ² whose default σ is 0 (no slope there),
    or built where the caller computes no gradients (a collector's no_grad, inference mode)."""
    base = reach.ReachModel
    members = {
        "float64": {
            "initial_state": lambda self, th, g: tuple(
                x.double() for x in base.initial_state(self, th, g)
            )
        },
        "unbounded actions": {"action_spec": Unbounded(shape=(1,), dtype=torch.float32)},
        "no observation": {
            "observation_dim": 0,
            "observe": TaskModel.observe,
            "observation_cov": TaskModel.observation_cov,
        },
        "a noise at 0": {
            "theta_space": reach.reach_theta_space()
            .with_range("sigma_v", 0.0, 0.1)
            .fix(sigma_v=0.0)
        },
        "no gradients": {},
    }[variant]
    model = _faulty(reach, **members)
    check_model(model)
    with torch.no_grad():
        TaskEnv(model, batch_size=(2,)).rollout(3)
    with torch.inference_mode():
        InverseRationalLoss(model, reach.controller_action_model(model), method="marginal")
    detached = _faulty(reach, transition=_detached)
    with torch.no_grad(), pytest.raises(ValueError, match="carries no gradient"):
        TaskEnv(detached)  # the probe's own gradients, whatever the caller's mode


def test_nan_observations_at_reset_name_observe(reach):
    """NaN observations (here for g < 0.8) went into the filter without a word; the reset that
    makes them names observe, and the first state's NaN names initial_state."""

    def observe(self, state, theta):
        root = (self.parameter(theta, "g") - 0.8).sqrt()
        return state[..., 1:] * root / root

    def initial_state(self, theta, generator):
        state, target = reach.ReachModel.initial_state(self, theta, generator)
        return state / (self.parameter(theta, "g") > 0.8), target  # at rest: 0/0 for g ≤ 0.8

    space = reach.reach_theta_space()
    theta = torch.stack([space.from_dict({"g": g}) for g in (1.2, 0.6)])
    for methods, name in [
        ({"observe": observe}, r"observe \(with observation_cov's noise\)"),
        ({"initial_state": initial_state}, "initial_state"),
    ]:
        env = TaskEnv(_faulty(reach, **methods), batch_size=(2,), theta=theta, seed=0)
        with pytest.raises(
            ValueError, match=rf"^model\.{name}: NaN or inf at the world's θ \(g=0\.6,"
        ):
            env.reset()
