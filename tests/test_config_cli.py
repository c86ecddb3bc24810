"""The configuration system and the ``irc`` command."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from matplotlib.image import imread

from irc_torchrl.algorithms.demo import format_summary
from irc_torchrl.cli import build_parser, main
from irc_torchrl.config import (
    Firefly1DConfig,
    config_to_dict,
    load_config,
    load_firefly2d_config,
    load_recording_fit_config,
    load_recovery2d_config,
    load_simulate_config,
)

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "q_iteration.n_envs=64",
    "q_iteration.rounds=1",
    "q_iteration.steps_per_round=30",
    "q_iteration.sweeps=10",
    "agents.n_agents=3",
    "agents.n_trials=20",
    "fit.n_screen=4",
    "fit.max_iter=8",
]


def test_shipped_yaml_equals_the_embedded_default():
    assert load_config(ROOT / "configs" / "firefly1d.yaml") == Firefly1DConfig()
    shipped = yaml.safe_load((ROOT / "configs" / "firefly1d.yaml").read_text())
    assert shipped == config_to_dict(Firefly1DConfig())


def test_overrides_reach_nested_fields_with_types():
    config = load_config(overrides=["agents.n_agents=7", "q_iteration.ridge=1e-3", "seed=4"])
    assert (config.agents.n_agents, config.q_iteration.ridge, config.seed) == (7, 1e-3, 4)
    assert isinstance(config.q_iteration.ridge, float)


@pytest.mark.parametrize(
    "override, message",
    [
        ("agents.n_agent=3", r"unknown key 'agents.n_agent' \(did you mean 'agents.n_agents'\?\)"),
        ("nonsense=1", "unknown key 'nonsense'"),
        ("agents.n_agents=many", "agents.n_agents='many' is not a valid int"),
        ("agents.world=elsewhere", r"agents.world must be one of \('known', 'shared'\)"),
        ("fit.curvature=newton", r"fit.curvature must be one of \('hessian', 'fisher', 'bfgs'\)"),
        ("fit.covariance=robust", r"fit.covariance must be one of \('hessian', 'sandwich'\)"),
        ("seed", "must look like key=value"),
        ("seed=-1", r"seed must be an integer in \[0, 2\*\*63\), got -1"),
        ("seed=9223372036854775808", r"seed must be an integer in \[0, 2\*\*63\), got 92233"),
        ("agents.n_agents=1.5", "agents.n_agents=1.5 is not a valid int"),
        ("agents.n_trials=true", "agents.n_trials=True is not a valid int"),
        ("flush_denormal=ture", "flush_denormal='ture' is not a valid bool"),
        ("threads=0", "threads must be positive, got 0"),
        ("agents.n_agents=0", "agents.n_agents must be positive, got 0"),
        ("agents.temperature=-1", "agents.temperature must be positive, got -1.0"),
        ("agents.temperature=.inf", "agents.temperature must be finite, got inf"),
        ("q_iteration.ridge=.inf", "q_iteration.ridge must be finite, got inf"),
        ("q_iteration.ridge=.nan", "q_iteration.ridge must be positive, got nan"),
        ("q_iteration.ridge=0", "q_iteration.ridge must be positive, got 0"),
        ("q_iteration.n_envs=-4", "q_iteration.n_envs must be positive, got -4"),
        ("q_iteration.gamma=1.5", r"q_iteration.gamma must lie in \(0, 1\]"),
        ("fit.workers=0", "fit.workers must be positive, got 0"),
        ("fit.n_screen=0", "fit.n_screen must be positive, got 0"),
        ("fit.n_starts=0", "fit.n_starts must be positive, got 0"),
        ("fit.n_starts=65", "fit.n_starts=65 exceeds fit.n_screen=64"),
        ("fit.max_iter=0", "fit.max_iter must be positive, got 0"),
        ("fit.workers=1.5", "fit.workers=1.5 is not a valid int"),
        ("agents.n_trials=[1", "override 'agents.n_trials=\\[1' is not valid YAML"),
    ],
)
def test_bad_overrides_are_clear_errors(override, message):
    with pytest.raises((KeyError, ValueError), match=message):
        load_config(overrides=[override])


@pytest.mark.parametrize(
    "load, override, message",
    [
        (load_simulate_config, "motor_noise=.inf", "motor_noise must be finite, got inf"),
        (load_recording_fit_config, "motor_noise=.inf", "motor_noise must be finite, got inf"),
        (load_recovery2d_config, "motor_noise=.inf", "motor_noise must be > 0 and finite, got inf"),
    ],
)
def test_infinite_numbers_are_refused_naming_the_field(load, override, message):
    """``.inf`` passes a bare ``> 0`` check and fails mid-run; it is refused before any work."""
    with pytest.raises(ValueError, match=message):
        load(overrides=[override])


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--seed", "99999999999999999999"],
        ["fit", "absent.csv", "--seed", str(2**63)],
        ["train", "--seed", "-1"],
    ],
)
def test_seeds_outside_64_bits_exit_2_naming_the_seed(argv, tmp_path, capsys):
    assert main([*argv, "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"irc {argv[0]}: error: --seed: expected an integer in [0, 2**63), ")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("argv", "key"),
    [
        (["fit", "absent.csv", "units.x=cm", "max_iter=5", "units.x=m"], "units.x"),
        (["simulate", "n_agents=2", "n_agents = 3"], "n_agents"),
        (["demo", "agents.n_agents=2", "--quiet", "agents.n_agents=3"], "agents.n_agents"),
        # an option that sets a config key, and the key set again
        (["demo", "seed=5", "--seed", "3"], "seed"),
        (["recover", "--device", "cpu", "device=cpu"], "device"),
        (["train", "--seed", "1", "seed=1"], "seed"),
        # a whole mapping and a key within it (the mapping replaced theta.g_v, unseen)
        (["demo", "agents={n_agents: 2}", "agents.n_agents=3"], "agents"),
        (["simulate", "theta.g_v=1.1", "theta={g_w: 1.0}"], "theta"),
    ],
)
def test_a_setting_given_twice_exits_2_naming_it(argv, key, tmp_path, capsys):
    """Two values for one key are refused before any work, not settled by their order."""
    # (threads=0: a run past the check would stop at the config, not train or fit)
    assert main([*argv, "threads=0", "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"irc {argv[0]}: error: {key}: given twice (")
    assert err.rstrip().endswith("give it once")
    assert not (tmp_path / "out").exists()


def test_flags_and_numbers_take_their_usual_spellings():
    config = load_config(overrides=["flush_denormal=no", "agents.n_agents=7.0", "fit.max_iter=9"])
    assert (config.flush_denormal, config.agents.n_agents, config.fit.max_iter) == (False, 7, 9)
    assert type(config.agents.n_agents) is int


def test_a_malformed_yaml_file_names_file_and_line(tmp_path):
    (tmp_path / "bad.yaml").write_text("agents:\n  n_agents: 3\n n_trials: 5\n")
    with pytest.raises(ValueError, match=r"bad.yaml is not valid YAML: .*\(line 3, column 2\)"):
        load_config(tmp_path / "bad.yaml")


def test_a_yaml_file_giving_a_key_twice_is_refused_naming_both_lines(tmp_path):
    """Plain YAML keeps the last of two values; a config file is refused as the command line
    is. A merge key's entries may still be overridden, as YAML means them to be."""
    (tmp_path / "twice.yaml").write_text("seed: 1\nagents:\n  n_agents: 3\n  n_agents: 4\n")
    with pytest.raises(
        ValueError,
        match=r"twice.yaml is not valid YAML: the key 'n_agents' is given twice "
        r"\(also on line 3\) \(line 4, column 3\)$",
    ):
        load_config(tmp_path / "twice.yaml")
    merged = "agents: {<<: {n_agents: 3, n_trials: 7}, n_agents: 5}\n"
    (tmp_path / "merged.yaml").write_text(merged)
    agents = load_config(tmp_path / "merged.yaml").agents
    assert (agents.n_agents, agents.n_trials) == (5, 7)


#: each shipped config file, the loader reading it and the command named for it
FILES = {
    "firefly1d.yaml": (load_config, "irc demo --task firefly1d"),
    "firefly2d.yaml": (load_firefly2d_config, "irc train"),
    "recover2d.yaml": (load_recovery2d_config, "irc recover or irc demo --task firefly2d"),
}


@pytest.mark.parametrize("given", FILES)
@pytest.mark.parametrize("loader", FILES)
def test_another_commands_config_file_is_refused_naming_both_commands(given, loader, tmp_path):
    """A shipped file handed to another command is named as that command's (rather than by
    its first key this one lacks), cited by a key no other command has; a file with a key of
    no command's, or with one key of another command's (misplaced), keeps the plain error."""
    load, this = FILES[loader]
    if given == loader:
        load(ROOT / "configs" / given)  # its own command reads it
        return
    other = FILES[given][1]
    with pytest.raises(
        KeyError, match=rf"{given} holds `{other}`'s settings \(e\.g\. '\w+'\), not `{this}`'s"
    ):
        load(ROOT / "configs" / given)
    data = {**yaml.safe_load((ROOT / "configs" / given).read_text()), "no_such_key": 1}
    (tmp_path / "typo.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(KeyError, match=r"config: unknown key '[a-z_]+'( \(did .*\))?; valid"):
        load(tmp_path / "typo.yaml")
    own = yaml.safe_load((ROOT / "configs" / loader).read_text())
    misplaced = next(key for key in data if key not in own)
    (tmp_path / "misplaced.yaml").write_text(yaml.safe_dump({**own, misplaced: data[misplaced]}))
    with pytest.raises(KeyError, match=rf"config: unknown key '{misplaced}'( \(did .*\))?; valid"):
        load(tmp_path / "misplaced.yaml")


def test_missing_config_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no file at"):
        load_config(tmp_path / "absent.yaml")


def test_a_config_file_that_is_not_utf8_text_or_is_a_folder_is_named(tmp_path):
    """A Latin-1 file said only that a byte could not be decoded (which file, not), and a
    folder that there was no file."""
    (tmp_path / "latin1.yaml").write_bytes("seed: 1  # café\n".encode("latin-1"))
    with pytest.raises(
        ValueError,
        match=r"^config: \S*latin1.yaml is not UTF-8 text \(invalid continuation byte at byte "
        r"14\); expected a YAML file$",
    ):
        load_config(tmp_path / "latin1.yaml")
    with pytest.raises(ValueError, match=r"^config: \S* is a folder; expected a YAML file$"):
        load_firefly2d_config(tmp_path)


@pytest.mark.parametrize(
    "text, message",
    [
        ("1: 2\n", "key 1 in FILE: expected a name"),
        ("agents:\n  1: 2\n", "key 1 in FILE under agents: expected a name"),
        ("true: 1\n", "key True in FILE: expected a name"),
        ("~: 1\n", "key None in FILE: expected a name"),
    ],
)
def test_a_key_that_is_not_a_name_is_refused_naming_it_and_its_file(text, message, tmp_path):
    """YAML reads ``1:``, ``true:`` and ``~:`` as a number, a flag and null: they raised
    AttributeError ('int' object has no attribute 'partition')."""
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(KeyError) as error:
        load_config(path)
    assert error.value.args[0] == f"config: {message.replace('FILE', str(path))}"


def test_a_mapping_override_keyed_by_a_number_is_refused_naming_its_field():
    """``theta_fixed={1: 0.5}`` failed as ``keywords must be strings``."""
    with pytest.raises(KeyError) as error:
        load_firefly2d_config(overrides=["theta_fixed={1: 0.5}"])
    expected = "config: key 1 in override 'theta_fixed={1: 0.5}' under theta_fixed: expected a name"
    assert error.value.args[0] == expected


def test_an_integer_written_with_an_exponent_is_that_integer(tmp_path):
    """YAML 1.1 reads ``1e6`` (no dot) and ``1.0e6`` (no exponent sign) as text: ``1e6`` was
    refused as not an int where ``1.0e+6`` was taken; a fraction is refused as before."""
    for written in ("1e6", "1.0e6", "1.0e+6", "1E6"):
        config = load_firefly2d_config(overrides=[f"ddpg.total_frames={written}"])
        assert config.ddpg.total_frames == 1_000_000 and type(config.ddpg.total_frames) is int
    (tmp_path / "c.yaml").write_text("ddpg:\n  total_frames: 2e5\n  lr_actor: 1e-5\n")
    ddpg = load_firefly2d_config(tmp_path / "c.yaml").ddpg
    assert (ddpg.total_frames, ddpg.lr_actor) == (200_000, 1e-5)
    with pytest.raises(ValueError, match=r"^config: ddpg.total_frames=1.5 is not a valid int$"):
        load_firefly2d_config(overrides=["ddpg.total_frames=1.5e0"])


@pytest.mark.parametrize(
    "load, setting",
    [
        (load_simulate_config, "device=cpu"),
        (load_simulate_config, "format=npz"),
        (load_recording_fit_config, "device=cpu"),
        (load_recording_fit_config, "method=map"),
        (load_recording_fit_config, "free=g_v"),
    ],
)
def test_a_setting_that_is_an_option_points_to_the_option(load, setting):
    """``irc simulate device=cpu`` or ``irc fit method=map`` listed the valid keys; the device
    and the method are options there, as the seed is. Only the command's own: irc recover
    has no ``--method``."""
    key = setting.partition("=")[0]
    hint = rf"unknown key '{key}' \(set by the option --{key}\); valid keys: "
    with pytest.raises(KeyError, match=hint):
        load([setting])
    with pytest.raises(KeyError) as error:
        load_recovery2d_config(None, ["method=map"])
    assert "option" not in str(error.value)


def test_help_lists_every_subcommand_with_a_purpose(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "demo train, simulate agents and recover their θ end to end (the main job)" in text


def test_unknown_key_on_the_command_line_exits_2(capsys, tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--quiet", "fit.max_iters=3"]) == 2
    assert "valid keys" in capsys.readouterr().err
    assert not (tmp_path / "summary.json").exists()


def test_demo_writes_a_reproducible_summary_and_figures(tmp_path, capsys):
    runs = []
    for name in ("a", "b"):
        out = tmp_path / name
        assert main(["demo", "--out", str(out), "--quiet", "--seed", "3", *TINY]) == 0
        runs.append(json.loads((out / "summary.json").read_text()))
    summary = runs[0]
    assert (summary["command"], summary["task"], summary["seed"]) == ("demo", "firefly1d", 3)
    assert len(summary["agents"]) == 3
    agent = summary["agents"][0]
    for key in ("theta_true", "theta_hat", "ci_low", "ci_high"):
        assert set(agent[key]) == {"g_a", "log_sigma0", "goal_radius", "move_cost"}
    assert agent["ci_low"]["g_a"] <= agent["theta_hat"]["g_a"] <= agent["ci_high"]["g_a"]
    # the fitted softmax temperature by name, in its natural unit, with its interval; where
    # the information does not bound it (one agent's, of this one-round Q) it runs from 0 to ∞
    # (null)
    for agent in summary["agents"]:
        assert agent["temperature"] == pytest.approx(math.exp(agent["nuisance"][0]), rel=1e-12)
        low, high = agent["temperature_ci"]
        assert low == 0 if high is None else 0 < low < agent["temperature"] < high
    assert sum(agent["temperature_ci"][1] is None for agent in summary["agents"]) == 1
    assert set(summary["parameters"]) == {"g_a", "log_sigma0"}
    for stats in summary["parameters"].values():
        assert 0 <= stats["coverage"] <= 1 and stats["median_ci_width"] > 0
    assert set(summary["timings"]) == {"train_s", "simulate_s", "fit_s"}
    strip = lambda s: {k: v for k, v in s.items() if k != "timings"}  # noqa: E731
    assert strip(runs[0]) == strip(runs[1])
    written = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())
    assert written["seed"] == 3 and written["agents"]["n_agents"] == 3
    for figure in ("q_function.png", "recovery.png", "dp_comparison.png"):
        assert (tmp_path / "a" / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the DP ratios: the grid's mean learned over mean optimal return, and the lowest per θ
    with np.load(tmp_path / "a" / "figures.npz") as arrays:
        learned, optimal = arrays["dp_learned"], arrays["dp_optimal"]
    assert summary["dp_ratio"] == pytest.approx(learned.mean() / optimal.mean(), rel=1e-6)
    assert summary["dp_ratio_min_per_theta"] == pytest.approx(min(learned / optimal), rel=1e-6)
    # irc report redraws every figure from summary.json and figures.npz, pixel for pixel
    figures = ("q_function.png", "dp_comparison.png", "recovery.png")
    drawn = {f: imread(tmp_path / "a" / f) for f in figures}
    for figure in tmp_path.joinpath("a").glob("*.png"):
        figure.unlink()
    capsys.readouterr()
    assert main(["report", str(tmp_path / "a")]) == 0
    assert capsys.readouterr().out.startswith(format_summary(summary))  # the demo's table
    for figure, pixels in drawn.items():
        assert np.array_equal(imread(tmp_path / "a" / figure), pixels), figure
    # without figures.npz the Q and DP figures cannot be drawn: said, not skipped in silence
    (tmp_path / "a" / "figures.npz").unlink()
    lacking = "report: no figures.npz in .*: the Q and DP figures are not drawn"
    with pytest.warns(UserWarning, match=lacking):
        assert main(["report", str(tmp_path / "a")]) == 0


def test_worker_processes_are_refused_off_the_cpu():
    """``workers`` > 1 shares a fit between CPU cores: another device is refused by name."""
    from irc_torchrl.algorithms.runtime import check_workers

    check_workers(1, "cuda:0")
    check_workers(4, "cpu")
    with pytest.raises(ValueError, match="workers: processes share a fit between CPU cores; "
                                         "expected 1 on cuda:0, got 2"):  # fmt: skip
        check_workers(2, "cuda:0")


@pytest.mark.parametrize("before", [False, True])
def test_a_runs_torch_settings_give_the_callers_back_afterwards(before):
    """Threads and denormal flushing return to what the caller had, either way: flushing
    was switched off afterwards even where the caller had it on."""
    import torch

    from irc_torchrl.algorithms.runtime import flushing_denormals, torch_settings

    if not torch.set_flush_denormal(False):
        pytest.skip("this CPU cannot flush denormals")
    threads = torch.get_num_threads()
    try:
        torch.set_flush_denormal(before)
        with torch_settings(threads + 1, not before):
            assert (torch.get_num_threads(), flushing_denormals()) == (threads + 1, not before)
        assert (torch.get_num_threads(), flushing_denormals()) == (threads, before)
    finally:
        torch.set_num_threads(threads)
        torch.set_flush_denormal(False)


@pytest.mark.parametrize(
    "override, message",
    [
        ("n_starts=17", "n_starts=17 exceeds n_screen=16"),
        ("lapse=0.5", r"lapse \(the fitted rate's start\) must be in \(0, 0.5\)"),
        ("calibrate=-1", "calibrate must be ≥ 0, got -1"),
        ("particles=-1", "particles must be ≥ 0, got -1"),
    ],
)
def test_recording_fit_settings_are_refused_just_past_their_bounds(override, message):
    """Each bound of ``irc fit``'s settings is where it says: one start more than the screened
    draws, a fitted lapse start at its ceiling 0.5, and −1 particles or calibrations fail."""
    with pytest.raises(ValueError, match=message):
        load_recording_fit_config([override])


def test_recording_fit_settings_at_their_bounds_are_accepted():
    """The values just inside those bounds load as given."""
    config = load_recording_fit_config(["n_starts=16", "lapse=0.49", "calibrate=0", "particles=0"])
    assert (config.n_starts, config.lapse, config.calibrate, config.particles) == (16, 0.49, 0, 0)


def test_a_yaml_file_and_overrides_combine_with_the_override_last(tmp_path):
    """The file's values replace the defaults and an override replaces the file's value."""
    (tmp_path / "c.yaml").write_text("agents:\n  n_agents: 5\nfit:\n  max_iter: 9\n")
    config = load_config(tmp_path / "c.yaml", ["agents.n_agents=7"])
    assert (config.agents.n_agents, config.fit.max_iter, config.agents.n_trials) == (7, 9, 100)


def test_a_quoted_flag_word_is_read_as_its_flag():
    """A quoted ``'no'`` (a string to YAML) is false and ``'yes'`` true, as unquoted ones are."""
    assert load_config(overrides=["flush_denormal='no'"]).flush_denormal is False
    assert load_config(overrides=["flush_denormal='yes'"]).flush_denormal is True


def test_a_list_override_is_cast_element_by_element():
    """Each element of a list takes the type of the default's elements: ``32.0`` is the
    integer 32, and a flag among widths is refused naming its index."""
    hidden = load_firefly2d_config(overrides=["ddpg.hidden=[32.0, 16]"]).ddpg.hidden
    assert hidden == [32, 16] and all(type(width) is int for width in hidden)
    with pytest.raises(ValueError, match=r"ddpg.hidden\[1\]=True is not a valid int"):
        load_firefly2d_config(overrides=["ddpg.hidden=[32, true]"])


def test_the_1d_demo_refuses_a_sandwich_with_too_few_trials_before_training(
    monkeypatch, tmp_path, capsys
):
    """3 trials per agent for 2 θ coordinates and the temperature: the sandwich's middle is
    singular. Refused naming the demo's own setting before Q-iteration (it failed after 75 s
    of training and simulation, naming ``covariance``)."""

    def no_work(*args, **kwargs):
        raise AssertionError("Q-iteration ran before the error")

    monkeypatch.setattr("irc_torchrl.algorithms.demo.train_factorised_q", no_work)
    argv = ["demo", "--out", str(tmp_path), "--quiet", "agents.n_trials=3"]
    assert main([*argv, "fit.covariance=sandwich"]) == 2
    err = capsys.readouterr().err
    assert "fit.covariance: 'sandwich' needs more trials per agent than fitted coordinates " in err
    assert "(3: 2 of θ, 1 nuisance); agent 0 has 3; expected fit.covariance=hessian" in err
