"""The ``irc`` command's plumbing (each option reaches the function doing the work, settings
after options, stray arguments, the ``--out`` check), the input checks at their edges, and the
arrays the 1D demo's figures are drawn from."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
from argparse import Namespace

import numpy as np
import pytest
import torch

from irc_torchrl import checks
from irc_torchrl.algorithms import demo, ensemble, recordings, recover2d
from irc_torchrl.algorithms.dp import optimal_values
from irc_torchrl.checkpoint import resolve_checkpoint
from irc_torchrl.cli import _check_arguments, _files_and_settings, build_parser, main
from irc_torchrl.config import RecordingFitConfig, SimulateConfig
from irc_torchrl.envs.firefly1d import Firefly1DModel


class Handed(Exception):
    """What a command handed the function that does its work (raised in its place)."""


def _handed(monkeypatch, module, name: str, argv: list[str]) -> tuple[tuple, dict]:
    """The arguments ``irc argv`` calls ``module.name`` with, stopping it there."""

    def stop(*args, **kwargs):
        raise Handed(args, kwargs)

    monkeypatch.setattr(module, name, stop)
    with pytest.raises(Handed) as handed:
        main(argv)
    return handed.value.args


def test_each_option_reaches_the_run_it_sets(monkeypatch, tmp_path):
    out = str(tmp_path / "out")
    (config, where), _ = _handed(
        monkeypatch, demo, "run_demo", ["demo", "--seed", "7", "--out", out]
    )
    assert (config.seed, str(where)) == (7, out)
    policy = tmp_path / "a.pt"
    policy.write_bytes(resolve_checkpoint("firefly2d").read_bytes())
    argv = ["recover", "--seed", "8", "--device", "cpu:0", "--checkpoint", str(policy)]
    argv += ["--out", out]
    (config, *_), _ = _handed(monkeypatch, recover2d, "run_recovery", argv)
    assert (config.seed, config.device, config.checkpoint) == (8, "cpu:0", str(policy))
    args, kwargs = _handed(monkeypatch, recover2d, "run_recovery", [*argv, "--resume"])
    assert (args[4], kwargs["keep"]) == (True, True)  # the fits kept, and read
    monkeypatch.chdir(tmp_path)
    args, kwargs = _handed(monkeypatch, recover2d, "run_recovery", ["demo", "--task", "firefly2d"])
    assert (args[4], kwargs["keep"]) == (False, False)  # minutes long: no stages to resume
    # the demos' outputs apart: the README's 2D demo in runs/demo refused the 1D one there
    assert args[1] == "runs/demo2d"
    assert str(_handed(monkeypatch, demo, "run_demo", ["demo"])[0][1]) == "runs/demo"
    argv = ["train", "--seed", "9", "--device", "cpu:0", "--out", out]
    (config,), kwargs = _handed(monkeypatch, ensemble, "train_ensemble", argv)
    assert (kwargs["seed"], config.device, kwargs["out"]) == (9, "cpu:0", out)
    # irc fit: an empty name in --free is skipped, a setting after the options is a setting
    argv = ["fit", "a.csv", "--out", out, "--free", "g_v,,g_w ", "--seed", "5", "max_iter=3"]
    (files, _, config), kwargs = _handed(monkeypatch, recordings, "fit_recordings", argv)
    assert (files, config.max_iter) == (["a.csv"], 3)
    assert (kwargs["free"], kwargs["seed"], kwargs["device"]) == (["g_v", "g_w"], 5, "cpu")


def _no_work(*args, **kwargs):
    raise AssertionError("work before the error")


def test_option_values_reach_the_config_as_given_not_read_as_yaml(monkeypatch, tmp_path, capsys):
    """Options went into the config as ``key=value`` read as YAML: ``--checkpoint "a #1/c.pt"``
    became ``a`` (a comment cut off), ``"b: x/c.pt"`` a mapping, ``yes`` True, and
    ``irc train --device "cpu #1"`` trained on the CPU."""
    monkeypatch.chdir(tmp_path)
    policy = resolve_checkpoint("firefly2d").read_bytes()
    for name in ("a #1/c.pt", "b: x/c.pt", "yes"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(policy)
        argv = ["recover", "--checkpoint", name, "--device", "cpu", "--out", "o"]
        (config, *_), _ = _handed(monkeypatch, recover2d, "run_recovery", argv)
        assert (config.checkpoint, config.device) == (name, "cpu")
    monkeypatch.setattr(ensemble, "train_ensemble", _no_work)
    assert main(["train", "--device", "cpu #1", "--out", "o", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("irc train: error: config: device must name a torch device")
    assert err.rstrip().endswith("got 'cpu #1'")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "theta.g_v=true"], "config: theta.g_v: expected a real number, got True"),
        (["fit", "a.csv", "theta.g_v=true"], "config: theta.g_v: expected a real number, got True"),
        (["fit", "a.csv", "theta.foo=1"], "theta.foo: unknown θ parameter 'foo'; valid names: "),
        (["fit", "a.csv", "--free", "g_v,foo"], "free: unknown θ parameter 'foo'; valid names: "),
        (["fit", "a.csv", "theta.g_v=100"], "theta.g_v: fixed g_v=100.0 outside its range [0.8, "),
    ],
)
def test_a_theta_setting_is_refused_naming_the_setting(
    argv, message, monkeypatch, tmp_path, capsys
):
    """``theta.g_v=true`` was taken as 1.0, and ``irc fit``'s errors about θ names and values
    did not say which setting they came from (``theta.foo=1`` and ``--free foo`` alike)."""
    monkeypatch.setattr(recordings, "simulate_agents", _no_work)
    monkeypatch.setattr(recordings, "read_trials", _no_work)
    assert main([*argv, "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith(f"irc {argv[0]}: error: {message}")


@pytest.mark.parametrize("logger, written", [("none", ""), ("csv", ", logs/")])
def test_trains_last_line_lists_logs_only_where_written(
    logger, written, monkeypatch, tmp_path, capsys
):
    """With ``logger=none`` the line still listed ``logs/``, which no run wrote."""
    best = {"success_rate": 0.5, "mean_return": 1.0, "mean_length": 20.0, "updates": 4}
    monkeypatch.setattr(ensemble, "train_ensemble", lambda *a, **k: Namespace(best=best))
    out = tmp_path / "o"
    assert main(["train", "--out", str(out), "--quiet", f"logger={logger}"]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last == f"wrote {out}/: checkpoint.pt, config.yaml, summary.json{written}"


def test_a_dotted_setting_after_the_options_is_a_setting_and_a_report_takes_none(tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["fit", "absent.csv", "--out", out, "--quiet", "no.such=1"]) == 2
    assert "error: config: unknown key 'no.such'" in capsys.readouterr().err  # read as a setting
    assert main(["report", str(tmp_path), "max_iter=3"]) == 2
    error = capsys.readouterr().err
    assert "DIR: max_iter=3 is a setting; irc report takes run folders only" in error


@pytest.mark.parametrize(
    "command, config", [("simulate", SimulateConfig()), ("fit", RecordingFitConfig())]
)
def test_the_defaults_a_commands_help_names_are_its_configs(command, config):
    parser = build_parser()
    (commands,) = (a for a in parser._actions if a.dest == "command")
    overrides = next(a for a in commands.choices[command]._actions if a.dest == "overrides")
    named = re.findall(r"(\w+) \((?:[^()]*?[;:,] )?default ([\w.]+)[;)]", overrides.help)
    keys = {"simulate": {"n_agents", "n_trials", "motor_noise", "lapse", "threads"},
            "fit": {"n_screen", "n_starts", "max_iter", "motor_noise", "lapse", "fit_lapse",
                    "threads", "workers"}}  # fmt: skip
    assert {key for key, _ in named} == keys[command]
    for key, default in named:
        value = getattr(config, key)
        assert str(value).lower() == default, key


def test_a_commands_warnings_are_one_line_like_its_errors(tmp_path):
    """Not Python's ``file:line: UserWarning`` with the source line that raised it; after the
    command, the process's warnings take Python's form again."""
    code = (
        "import warnings\n"
        "from irc_torchrl import cli\n"
        "def warn(args):\n"
        "    warnings.warn('report: no trials/ in here')\n"
        "    return 0\n"
        "cli._report = warn\n"
        f"assert cli.main(['report', {str(tmp_path)!r}]) == 0\n"
        "warnings.warn('after the command')\n"
    )
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    lines = ran.stderr.splitlines()
    assert lines[0] == "irc report: warning: no trials/ in here"
    assert "UserWarning: after the command" in lines[1]  # Python's own form again


def test_a_setting_without_its_equals_sign_is_refused_saying_the_form(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["fit", "a.csv", "--out", str(tmp_path), "max_iter", "1"])
    err = capsys.readouterr().err
    assert "unrecognized arguments: max_iter 1 (irc fit takes settings as key=value)" in err
    with pytest.raises(SystemExit):  # a mistyped option is not a setting
        main(["fit", "a.csv", "--out", str(tmp_path), "--seeed", "1"])
    assert capsys.readouterr().err.strip().endswith("unrecognized arguments: --seeed 1")


def test_a_recording_named_like_a_setting_is_a_recording(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "n=1.csv").write_text("")
    args = Namespace(files=["n=1.csv", "n=2"], overrides=["max_iter=3"])
    assert _files_and_settings(args) == (["n=1.csv"], ["n=2", "max_iter=3"])


def test_out_holding_another_commands_summary_is_refused_but_a_short_recovery_may_rerun(tmp_path):
    (tmp_path / "summary.json").write_text(json.dumps({"command": "recover", "task": "firefly2d"}))
    parse = build_parser().parse_args
    (tmp_path / "notes").write_text("")  # a file by any name, a suffix or none
    with pytest.raises(ValueError, match="--out: expected a folder, .*notes is a file"):
        _check_arguments(parse(["train", "--out", str(tmp_path / "notes")]))
    _check_arguments(parse(["demo", "--task", "firefly2d", "--out", str(tmp_path)]))
    written = r"summary.json of irc recover \(or irc demo --task firefly2d\), which irc demo"
    with pytest.raises(ValueError, match=written):
        _check_arguments(parse(["demo", "--out", str(tmp_path)]))


def test_a_key_error_prints_its_message_without_quotes(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path / "o"), "theta.nosuch=1"]) == 2
    assert capsys.readouterr().err.startswith("irc simulate: error: theta: unknown θ parameter")


@pytest.mark.parametrize("command", ["train", "simulate", "fit", "recover"])
def test_a_task_of_discrete_actions_is_pointed_to_its_own_route(tmp_path, capsys, command):
    """The 1D task named to a command of the DDPG policy: fit said to `irc train` its policy,
    and train said its actions were not continuous, naming no way to fit one's recordings."""
    files = ["a.csv"] if command == "fit" else []
    model = "irc_torchrl.envs.firefly1d:Firefly1DModel"
    assert main([command, *files, "--out", str(tmp_path / "o"), "--model", model]) == 2
    err = capsys.readouterr().err
    assert err.startswith(
        f"irc {command}: error: --model: Firefly1DModel's actions are "
        "Categorical []; expected continuous actions [da]"
    )
    assert "train_factorised_q and recover_agents" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_the_demos_help_names_the_size_it_puts_over_a_config_file(capsys):
    """``irc demo --task firefly2d --config FILE`` replaces four of the file's values by the
    demo's: its help says which, as the code has them."""
    from irc_torchrl.algorithms.recover2d import DEMO_OVERRIDES

    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    assert " ".join(DEMO_OVERRIDES) in " ".join(capsys.readouterr().out.split())


# --- the input checks at their edges -----------------------------------------------------------
TENSOR = torch.tensor(2.0)
REFUSED = {
    checks.real: [True, np.True_, "1.5", torch.ones(1), None],
    checks.positive_number: [0, -0.0, -1, math.nan, math.inf, True, "2"],
    checks.count: [0, -1, True, 2.0, np.float64(3), math.nan],
    checks.seed: [-1, 2**64, True, 1.0, np.float64(3)],
}
ACCEPTED = {
    checks.real: [(math.inf, math.inf), (-0.0, 0.0), (TENSOR, 2.0), (np.int64(3), 3.0)],
    checks.positive_number: [(5e-324, 5e-324), (TENSOR, 2.0), (np.float32(0.5), 0.5)],
    checks.count: [(1, 1), (np.int64(4), 4), (torch.tensor(3), 3)],
    checks.seed: [(0, 0), (2**64 - 1, 2**64 - 1), (np.uint64(7), 7)],
}


@pytest.mark.parametrize(
    ("check", "value"), [(c, v) for c, values in REFUSED.items() for v in values]
)
def test_number_checks_refuse_what_is_not_their_kind_naming_the_field(check, value):
    with pytest.raises(ValueError, match=r"^speed: expected an? ") as error:
        check("speed", value)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    ("check", "value", "number"), [(c, *v) for c, values in ACCEPTED.items() for v in values]
)
def test_number_checks_give_the_plain_number_at_their_edges(check, value, number):
    result = check("speed", value)
    assert result == number and type(result) is type(number)


def test_count_and_positive_take_their_lower_bounds_and_refuse_past_them():
    assert checks.count("n", 0, least=0) == 0
    with pytest.raises(ValueError, match="n: expected an integer ≥ 2, got 1"):
        checks.count("n", 1, least=2)
    checks.positive(a=1e-300, b=3)
    for value, word in (
        (0, "positive"),
        (-0.0, "positive"),
        (math.nan, "positive"),
        (math.inf, "finite"),
    ):
        with pytest.raises(ValueError, match=f"config: a must be {word}, got"):
            checks.positive(a=value)


def test_shown_keeps_one_line_of_at_most_the_width():
    assert checks.shown(torch.zeros(3, 3)) == "tensor([[0., 0., 0.], [0., 0., 0.], [0., 0., 0.]])"
    cut = checks.shown("x" * 200, width=20)
    assert len(cut) == 20 and cut.endswith("…") and cut.startswith("'xxx")


@dataclasses.dataclass
class Inner:
    n: int = 1
    rate: float = 0.5
    flag: bool = False
    names: list = dataclasses.field(default_factory=lambda: ["a"])
    units: dict = dataclasses.field(default_factory=dict)
    device: str = "cpu"


@dataclasses.dataclass
class Outer:
    seed: int = 0
    inner: Inner = dataclasses.field(default_factory=Inner)


def test_check_fields_stores_the_plain_forms_of_what_stands_for_each_default():
    config = Outer(seed=np.int64(2**63 - 1), inner=Inner(n=torch.tensor(3), rate=2, flag=np.True_))
    config.inner.names, config.inner.device = ("b", "c"), torch.device("cpu")
    checks.check_fields(config)
    assert config == Outer(2**63 - 1, Inner(3, 2.0, True, ["b", "c"], {}, "cpu"))
    assert type(config.seed) is int and type(config.inner.rate) is float


@pytest.mark.parametrize(
    ("inner", "seed", "message"),
    [
        ({"n": True}, 0, "inner.n=True is not a valid int"),
        ({"n": 1.5}, 0, "inner.n=1.5 is not a valid int"),
        ({"rate": False}, 0, "inner.rate=False is not a valid float"),
        ({"flag": 1}, 0, "inner.flag=1 is not a valid bool"),
        ({"names": "ab"}, 0, "inner.names='ab' is not a valid list"),
        ({"names": {"a": 1}}, 0, "inner.names={'a': 1} is not a valid list"),
        ({"names": ["a", 2]}, 0, "inner.names=['a', 2] is not a valid list"),
        ({"units": [("x", "cm")]}, 0, "inner.units=[('x', 'cm')] is not a valid dict"),
        ({"device": 0}, 0, "inner.device=0 is not a valid str"),
        ({}, 2**63, "seed must be an integer in [0, 2**63), got 9223372036854775808"),
        ({}, -1, "seed must be an integer in [0, 2**63), got -1"),
    ],
)
def test_check_fields_refuses_a_value_that_cannot_stand_for_its_default(inner, seed, message):
    with pytest.raises(ValueError, match="^" + re.escape(f"config: {message}")):
        checks.check_fields(Outer(seed=seed, inner=Inner(**inner)))


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("meta", "device: 'meta' tensors hold no values"),
        ("hpu", "device: 'hpu' is not usable here"),  # torch.hpu: no such module
        ("nonsense", "device: Expected one of"),
        pytest.param(
            "cuda:0",
            "device: 'cuda:0' requested but torch.cuda.is_available() is False",
            marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU"),
        ),
    ],
)
def test_a_device_this_machine_cannot_use_is_refused_in_one_line(name, message):
    with pytest.raises(ValueError) as error:
        checks.resolve_device(name)
    assert str(error.value).startswith(message) and "\n" not in str(error.value)


# --- the 1D demo's figure arrays ---------------------------------------------------------------
class Features(torch.nn.Module):
    """A stand-in Q network returning three of its belief features: the believed offset to the
    target (scaled to the target range), the time in the trial, the goal probability."""

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return features[..., [0, 3, 4]]


def test_the_demos_q_figure_reads_q_at_the_start_of_a_trial_at_the_offset_it_plots():
    model = Firefly1DModel()
    optimal, learned = (
        torch.tensor([[1.0, 3.0], [2.0, 2.0]]),
        torch.tensor([[1.0, 2.0], [0.0, 4.0]]),
    )
    grid = torch.tensor([[0.7, 1.0], [1.3, 1.0]], dtype=torch.float64)
    arrays = demo._figure_arrays(model, Features(), grid, optimal, learned, gamma=1.0)
    relative = arrays["q_relative"]
    assert relative[0] == -model.target_range and relative[-1] == model.target_range
    np.testing.assert_allclose(arrays["q_learned"][:, 0], relative / model.target_range, atol=1e-6)
    np.testing.assert_array_equal(arrays["q_learned"][:, 1], 0)  # the trial's first step
    default = model.theta_space.default(torch.float64)
    np.testing.assert_array_equal(arrays["theta"], default)
    assert arrays["theta_names"].tolist() == list(model.theta_space.names)
    exact = optimal_values(model, default.unsqueeze(0), torch.as_tensor(relative))[0]
    np.testing.assert_array_equal(arrays["q_optimal"], exact)
    # far right of the target the exact Q walks left, far left it walks right
    assert arrays["q_optimal"][-1].argmax() == 0 and arrays["q_optimal"][0].argmax() == 2
    np.testing.assert_array_equal(arrays["dp_theta"], grid)
    np.testing.assert_array_equal(arrays["dp_optimal"], [2.0, 2.0])
    np.testing.assert_array_equal(arrays["dp_learned"], [1.5, 2.0])


def test_the_demo_summary_line_lists_the_ratios_and_every_timing():
    stats = {
        "coverage": 1.0, "coverage_ci": [0.5, 1.0], "z_median": None, "z_robust_sd": 1.0,
        "median_abs_error": 0.1, "median_rel_error": 0.2, "median_range_error": 0.05,
        "median_ci_width": 0.3,
    }  # fmt: skip
    summary = {
        "parameters": {"g_a": stats},
        "dp_ratio": 0.98765,
        "dp_ratio_min_per_theta": 0.9123,
        "timings": {"train_s": 1.04, "simulate_s": 2.0, "fit_s": 3.46},
    }
    last = demo.format_summary(summary).splitlines()[-1]
    assert last == "DP ratio 0.9877 (min per θ 0.912); train_s 1.0, simulate_s 2.0, fit_s 3.5"


def test_a_recording_after_the_options_is_a_recording(tmp_path, monkeypatch, capsys):
    """argparse gave the setting before the options to FILE and refused the file after them."""
    missing = str(tmp_path / "missing.csv")  # named as missing, not as a stray argument
    assert main(["fit", "max_iter=3", "--out", str(tmp_path / "out"), missing]) == 2
    assert f"error: {missing}: no such file or folder" in capsys.readouterr().err
    recording = tmp_path / "a.csv"
    recording.write_text("")
    argv = ["fit", "max_iter=3", "--out", str(tmp_path / "out"), str(recording), "n_starts=2"]
    (files, _, config), _ = _handed(monkeypatch, recordings, "fit_recordings", argv)
    assert (files, config.max_iter, config.n_starts) == ([str(recording)], 3, 2)


def test_a_fit_converged_early_ends_its_progress_bar_at_100_percent():
    """A fit converged after 41 of its 80 iterations left 'fit (marginal): 51%| 41/80', which
    reads as a run that stopped part-way."""
    import io

    from tqdm.auto import tqdm

    from irc_torchrl.algorithms.runtime import finish

    shown = io.StringIO()
    with tqdm(total=80, desc="fit", file=shown) as bar:
        bar.update(41)
        finish(bar)
    assert shown.getvalue().rstrip().split("\r")[-1].startswith("fit: 100%|##########| 41/41 ")


def test_each_stage_of_a_recovery_ends_its_progress_bar_when_the_next_begins(tmp_path, monkeypatch):
    """The simulation's bar stayed open through the fits, its clock and rate running on
    ('simulate: 60/60 [02:30, 2.51s/it]' for a simulation of seconds)."""
    from tensordict import TensorDict

    events = []

    class Bar:
        def __init__(self, total: int, desc: str, disable: bool) -> None:
            self.desc, self.n, self.total = desc, 0, total
            events.append(("open", desc))

        def update(self, n: int) -> None:
            self.n += n

    def stages(config, progress, model, kept):
        for stage, n in (("simulate", 3), ("map", 2), ("marginal", 2)):
            for i in range(n):
                progress(stage, i, n)
        return TensorDict(), {}, {}

    monkeypatch.setattr(recover2d, "tqdm", Bar)
    monkeypatch.setattr(recover2d, "finish", lambda bar: events.append(("finish", bar.desc)))
    monkeypatch.setattr(recover2d, "recover_firefly2d", stages)
    monkeypatch.setattr(recover2d, "write_recovery", lambda *args: None)
    recover2d.run_recovery(recover2d.Recovery2DConfig(), tmp_path, keep=False)
    assert events == [
        (kind, desc)
        for desc in ("simulate", "fit (map)", "fit (marginal)")
        for kind in ("open", "finish")
    ]


def test_a_notebook_progress_bar_ended_early_fills_its_widget():
    """tqdm.notebook draws the bar as a widget whose length is set only when the bar is made,
    so a fit converged early showed a bar half full beside '100%'."""
    from types import SimpleNamespace

    from irc_torchrl.algorithms.runtime import finish

    widget = SimpleNamespace(max=80)
    bar = SimpleNamespace(n=41, total=80, refresh=lambda: None, close=lambda: None)
    bar.container = SimpleNamespace(children=(None, widget, None))
    finish(bar)
    assert (bar.total, widget.max) == (41, 41)
