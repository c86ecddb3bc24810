"""Resuming a long run: each fit kept as it finishes, read back by a run of the same key only,
and an interrupted recovery or fit of recordings resumed to the numbers of an uninterrupted
one."""

from __future__ import annotations

import dataclasses
import importlib
import json
import site
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from irc_torchrl.algorithms import recordings, recover2d
from irc_torchrl.algorithms import stages as stages_module
from irc_torchrl.algorithms.fit import FitResult
from irc_torchrl.algorithms.recover2d import Recovery2DConfig, recovery_stages, run_recovery
from irc_torchrl.algorithms.stages import Stages, format_resumed, stage_key, staged_by
from irc_torchrl.checkpoint import read_weights, resolve_checkpoint
from irc_torchrl.cli import main
from irc_torchrl.config import FitConfig, RecordingFitConfig
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.objectives.fisher import fisher_intervals
from irc_torchrl.theta import ThetaSpace

#: a recovery small enough for seconds, with both estimators and two calibration datasets
TINY = dict(
    n_prior_agents=2, n_mistaken_agents=0, n_trials=4, calibrate=2, threads=1,
    fit=FitConfig(n_screen=2, n_starts=1, max_iter=2, curvature="bfgs"),
)  # fmt: skip


class Interrupted(Exception):
    """A run stopped part-way (a killed job)."""


def _result(seed: int, n: int = 3) -> FitResult:
    """A fit result of ``n`` agents with random θ̂, curvature and nuisance."""
    space = Firefly2DModel().theta_space
    g = torch.Generator().manual_seed(seed)
    theta = space.sample((n,), generator=g, dtype=torch.float64)
    k = len(space.free_names)
    root = torch.randn(n, k, k, generator=g, dtype=torch.float64)
    hessian = root @ root.transpose(1, 2) + torch.eye(k, dtype=torch.float64)
    u = space.to_unconstrained(theta)[:, space.free_mask]
    information = torch.eye(k + 2, dtype=torch.float64).repeat(n, 1, 1)
    information[:, :k, :k] = hessian
    return FitResult(
        theta_hat=theta,
        nuisance=torch.randn(n, 2, generator=g, dtype=torch.float64),
        log_likelihood=torch.randn(n, generator=g, dtype=torch.float64),
        intervals=fisher_intervals(space, theta, u, hessian),
        converged=torch.rand(n, generator=g) < 0.5,
        iterations=7,
        names=space.names,
        information=information,
    )


def _same(a: FitResult, b: FitResult) -> bool:
    """Whether two results are equal in every field, bit for bit."""
    state_a, state_b = a.state_dict(), b.state_dict()
    tensors = [(state_a[k], state_b[k]) for k in FitResult._PER_AGENT]
    tensors += [(state_a["intervals"][k], state_b["intervals"][k]) for k in state_a["intervals"]]
    plain = (a.iterations, list(a.names)) == (b.iterations, list(b.names))
    return plain and all(torch.equal(x, y) and x.dtype == y.dtype for x, y in tensors)


def test_a_stage_is_read_back_only_by_a_resuming_run_of_its_key(tmp_path):
    """Saved bit for bit with its seconds; a run not resuming, or of another key, fits again
    (and overwrites); an unreadable stage file is fitted again, not an error; no folder keeps
    nothing."""
    calls = []

    def work(seed: int):
        def fit() -> FitResult:
            calls.append(seed)
            return _result(seed)

        return fit

    first, seconds = Stages(tmp_path, "k1").fit("fit_map", work(0))
    assert calls == [0] and (tmp_path / "fit_map.pt").is_file() and seconds >= 0
    again = Stages(tmp_path, "k1", resume=True)
    read, read_seconds = again.fit("fit_map", work(1))
    assert calls == [0] and again.reused == ["fit_map"] and read_seconds == seconds
    assert _same(read, first)
    assert not _same(Stages(tmp_path, "k1").fit("fit_map", work(2))[0], first)  # not resuming
    other = Stages(tmp_path, "k2", resume=True)
    assert _same(other.fit("fit_map", work(3))[0], _result(3)) and other.reused == []
    assert calls == [0, 2, 3]
    path = tmp_path / "fit_map.pt"
    path.write_bytes(path.read_bytes()[:-200])  # truncated
    assert _same(Stages(tmp_path, "k2", resume=True).fit("fit_map", work(4))[0], _result(4))
    nowhere = Stages(None, "k1", resume=True)
    nowhere.fit("fit_map", work(5))
    assert calls[-1] == 5 and nowhere.reused == []


def test_a_check_is_kept_and_read_back_as_tensors_by_name(tmp_path):
    """A check's tensors come back bit for bit with its seconds; a stage holding anything else
    (a fit's, under the same name) is run again, not misread."""
    calls = []

    def work() -> dict[str, torch.Tensor]:
        calls.append(1)
        return {"gap": torch.randn(3, dtype=torch.float64), "ess": torch.arange(3.0)}

    first, seconds = Stages(tmp_path, "k").check("particles20_at_theta_hat_map", work)
    again = Stages(tmp_path, "k", resume=True)
    read, read_seconds = again.check("particles20_at_theta_hat_map", work)
    assert len(calls) == 1 and read_seconds == seconds and read.keys() == first.keys()
    assert all(torch.equal(read[k], first[k]) and read[k].dtype == first[k].dtype for k in read)
    Stages(tmp_path, "k").fit("fit_map", lambda: _result(0))
    misnamed = Stages(tmp_path, "k", resume=True)
    misnamed.check("fit_map", work)
    assert len(calls) == 2 and misnamed.reused == []


def test_pruning_keeps_the_stages_of_this_key_only(tmp_path):
    Stages(tmp_path, "old").fit("calibration3_map", lambda: _result(0))
    stages = Stages(tmp_path, "new")
    stages.fit("fit_map", lambda: _result(1))
    Stages(tmp_path, "new").fit("calibration2_map", lambda: _result(2))  # unused, same key
    (tmp_path / "notes.pt").write_text("not a stage")
    (tmp_path / ".fit_marginal.pt.x1y2z3w4.irc-tmp").write_text("")  # a save killed part-way
    stages.prune()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration2_map.pt", "fit_map.pt"]


def test_the_key_follows_settings_checkpoint_data_and_a_tasks_source(tmp_path):
    checkpoint = resolve_checkpoint("firefly2d")
    copy = tmp_path / "copy.pt"
    copy.write_bytes(checkpoint.read_bytes())
    data = TensorDict({"state": torch.zeros(2, 3)}, batch_size=[2])
    key = stage_key({"seed": 0}, checkpoint, None, [data])
    assert key == stage_key({"seed": 0}, copy, None, [data.clone()])  # contents, not paths
    copy.write_bytes(checkpoint.read_bytes() + b"\0")
    changed = [
        stage_key({"seed": 1}, checkpoint, None, [data]),
        stage_key({"seed": 0}, copy, None, [data]),
        stage_key({"seed": 0}, checkpoint, None, [data.apply(lambda x: x + 1)]),
        stage_key({"seed": 0}, checkpoint, None, [data, data]),
        stage_key({"seed": 0}, checkpoint, Firefly2DModel(), [data]),
    ]
    assert len({key, *changed}) == 6
    assert stage_key({"seed": 0}, "firefly2d", None, [data]) == key  # a packaged name
    # a task's θ space caches its bounds once used: a run resumed in the same process (the
    # first run's fits filled it) read none of its stages
    model = Firefly2DModel()
    unused = stage_key({"seed": 0}, checkpoint, model, [data])
    model.theta_space.normalise(model.theta_space.default())
    assert stage_key({"seed": 0}, checkpoint, model, [data]) == unused
    # a tensor in the settings by its bytes: torch prints a long one shortened, and a key of
    # its print read another run's fits as this one's
    values = torch.arange(2000.0)
    edited = values.clone()
    edited[1000] = -5
    assert str(values) == str(edited)
    assert stage_key({"t": values}, checkpoint) != stage_key({"t": edited}, checkpoint)


def test_a_recoverys_key_reads_the_checkpoints_contents_the_task_and_the_trials(tmp_path):
    """The same checkpoint under another path keys the same stages; a task built otherwise,
    or other simulated trials, other ones."""
    copy = tmp_path / "copy.pt"
    copy.write_bytes(resolve_checkpoint("firefly2d").read_bytes())
    packaged = recovery_stages(Recovery2DConfig(**TINY), tmp_path)
    assert recovery_stages(Recovery2DConfig(**TINY, checkpoint=str(copy)), tmp_path).key == (
        packaged.key
    )
    settings = {"seed": 0}
    checkpoint = resolve_checkpoint("firefly2d")
    shorter = stage_key(settings, checkpoint, Firefly2DModel(max_steps=40))
    assert shorter != stage_key(settings, checkpoint, Firefly2DModel())
    trials = TensorDict({"state": torch.zeros(2, 3)}, batch_size=[2])
    keys = []
    for data in (trials, trials.clone(), trials + 1):
        stages = recovery_stages(Recovery2DConfig(**TINY), tmp_path)
        stages.include([data])
        keys.append(stages.key)
    assert keys[0] == keys[1] != keys[2] and packaged.key not in keys


def test_a_fit_of_recordings_is_keyed_by_what_its_fits_depend_on(tmp_path):
    """Free parameters, seed, device, any setting the fits read, the recordings and the
    checkpoint key other stages; the method (map's fit is the same whichever follows), the
    particle check and the calibration's size and tail do not."""
    model = Firefly2DModel()
    checkpoint = resolve_checkpoint("firefly2d")
    data = [TensorDict({"state": torch.zeros(4, 3)}, batch_size=[4])]
    settings = {"free": ["g_v", "g_w"], "seed": 0, "device": "cpu"}

    def key(config=None, changed=None, recorded=data, policy=checkpoint):
        given = {**settings, **(changed or {})}
        config = config or RecordingFitConfig()
        return recordings.recording_stages(
            tmp_path, config, policy, model, recorded, **given, resume=True
        ).key

    same = [
        key(RecordingFitConfig(particles=1000)),
        key(RecordingFitConfig(calibrate=3, calibration_tail="shrunk")),
    ]
    copy = tmp_path / "copy.pt"
    copy.write_bytes(checkpoint.read_bytes() + b"\0")
    other = [
        key(changed={"free": ["g_v"]}),
        key(changed={"seed": 1}),
        key(changed={"device": "cuda:0"}),
        key(RecordingFitConfig(max_iter=7)),
        key(RecordingFitConfig(motor_noise=0.2)),
        key(RecordingFitConfig(units={"x": "cm"})),
        key(RecordingFitConfig(theta={"goal_radius": 0.3})),
        key(recorded=[data[0] + 1]),
        key(policy=copy),
    ]
    other.append(
        recordings.recording_stages(
            tmp_path, RecordingFitConfig(), checkpoint, Firefly2DModel(max_steps=40), data,
            **settings,
        ).key
    )  # fmt: skip
    assert set(same) == {key()} and len({key(), *other}) == len(other) + 1


class _Tuned(Firefly2DModel):
    """A task holding a tensor and a plain object (whose repr names its address)."""

    def __init__(self, scale: float = 1.0):
        super().__init__()
        self.scale = torch.tensor([scale])
        self.helper = object()


def test_what_a_task_holds_keys_its_stages_and_object_addresses_do_not():
    """Its tensors (also inside a container, where a repr rounds them), its θ space's defaults
    and its action bounds (which their reprs do not show) key other stages; an object's address
    and a set's order (both of the process) do not."""
    checkpoint = resolve_checkpoint("firefly2d")
    keys = [stage_key({}, checkpoint, model) for model in (_Tuned(), _Tuned(), _Tuned(2.0))]
    assert keys[0] == keys[1] != keys[2]
    base = stage_key({}, checkpoint, Firefly2DModel())
    nested = Firefly2DModel()
    nested.extra = {"w": torch.tensor([1.00001])}
    space = Firefly2DModel().theta_space
    shifted = [dataclasses.replace(p, default=0.9) if p.name == "g_v" else p
               for p in space.parameters]  # fmt: skip
    wider = Firefly2DModel()
    wider.action_spec = Bounded(-2.0, 2.0, shape=wider.action_spec.shape)
    changed = [
        stage_key({}, checkpoint, nested),
        stage_key({}, checkpoint, Firefly2DModel(theta_space=ThetaSpace(shifted, space.fixed))),
        stage_key({}, checkpoint, wider),
    ]
    nested.extra = {"w": torch.tensor([1.00002])}
    changed.append(stage_key({}, checkpoint, nested))
    assert len({base, *changed}) == 5
    tagged = Firefly2DModel()
    tagged.tags = frozenset(f"tag{i}" for i in range(20))
    code = (
        "from irc_torchrl.algorithms.stages import stage_key\n"
        "from irc_torchrl.checkpoint import resolve_checkpoint\n"
        "from irc_torchrl.envs.firefly2d import Firefly2DModel\n"
        "m = Firefly2DModel()\n"
        "m.tags = frozenset(f'tag{i}' for i in range(20))\n"
        "print(stage_key({}, resolve_checkpoint('firefly2d'), m))\n"
    )
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert other.stdout.strip() == stage_key({}, checkpoint, tagged)  # another hash seed


class _Unprintable:
    """An object without attributes whose repr raises."""

    __slots__ = ()

    def __repr__(self) -> str:
        raise RuntimeError("no repr")


def test_a_tasks_numpy_arrays_key_its_stages_in_full_and_a_raising_repr_does_not_stop_it():
    """An array longer than NumPy's repr shows (1000 elements) keys by every element, one of
    objects by its contents; an object whose repr raises is keyed by its type."""
    checkpoint = resolve_checkpoint("firefly2d")
    keys = []
    for table in (np.zeros(2000), np.zeros(2000), np.eye(1, 2000, 1000).ravel()):
        model = Firefly2DModel()
        model.table = table
        keys.append(stage_key({}, checkpoint, model))
    boxed = []
    for item in ("a", "a", "b"):
        model = Firefly2DModel()
        model.boxes = np.array([item, None], dtype=object)
        boxed.append(stage_key({}, checkpoint, model))
    assert keys[0] == keys[1] != keys[2] and boxed[0] == boxed[1] != boxed[2]
    model = Firefly2DModel()
    model.odd = _Unprintable()
    odd = stage_key({}, checkpoint, model)
    model.odd = frozenset([_Unprintable()])
    assert len({odd, stage_key({}, checkpoint, model), *keys, *boxed}) == 6
    records = []  # a structured array with an object field: by its contents, not its pointers
    for _ in range(2):
        model = Firefly2DModel()
        record = (int("123456"), 1.0)  # an equal int, a new object each time
        model.records = np.array([record], dtype=[("id", object), ("v", float)])
        records.append(stage_key({}, checkpoint, model))
    assert records[0] == records[1]


def test_a_tasks_key_reads_the_user_code_its_class_runs(tmp_path, monkeypatch):
    """The source of a task's own file, of a base class's file and of a helper module they
    import key its stages (an edit of any one keys others), by name, not by where they lie;
    installed packages and this library do not enter as files."""
    (tmp_path / "shapes.py").write_text("def radius():\n    return 0.3\n")
    (tmp_path / "base.py").write_text(
        "from irc_torchrl.envs.firefly2d import Firefly2DModel\n"
        "class Base(Firefly2DModel):\n    pass\n"
    )
    (tmp_path / "task.py").write_text(
        "import numpy\nfrom shapes import radius\nfrom base import Base\n"
        "class Task(Base):\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("shapes", "base", "task"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    task = importlib.import_module("task").Task
    assert stages_module._user_sources(Firefly2DModel) == {}
    assert list(stages_module._user_sources(task)) == ["base", "shapes", "task"]
    checkpoint = resolve_checkpoint("firefly2d")
    keys = [stage_key({}, checkpoint, task())]
    for name in ("shapes.py", "base.py", "task.py"):
        path = tmp_path / name
        path.write_text(path.read_text() + "# edited\n")
        keys.append(stage_key({}, checkpoint, task()))
    assert len(set(keys)) == 4
    moved = tmp_path / "moved"  # the same code elsewhere (a cluster job's own copy)
    moved.mkdir()
    for name in ("shapes.py", "base.py", "task.py"):
        (moved / name).write_bytes((tmp_path / name).read_bytes())
        monkeypatch.delitem(sys.modules, name[:-3])
    monkeypatch.syspath_prepend(str(moved))
    elsewhere = importlib.import_module("task").Task
    assert Path(sys.modules["task"].__file__).parent == moved
    assert stage_key({}, checkpoint, elsewhere()) == keys[-1]


def test_a_task_in_a_package_is_keyed_by_every_file_of_it_wherever_it_is_installed(
    tmp_path, monkeypatch
):
    """Every module of the task's package keys it, imported or not (so a later import does not
    change the key), also where the package is installed among site-packages; another
    installed package it uses does not."""
    package = tmp_path / "labtask"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "extra.py").write_text("SCALE = 2\n")
    (package / "task.py").write_text(
        "from irc_torchrl.envs.firefly2d import Firefly2DModel\nimport helpers\n"
        "class LabTask(Firefly2DModel):\n    pass\n"
    )
    (tmp_path / "helpers.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("labtask", "labtask.task", "labtask.extra", "helpers"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    task = importlib.import_module("labtask.task").LabTask
    files = ["helpers", "labtask/__init__.py", "labtask/extra.py", "labtask/task.py"]
    assert list(stages_module._user_sources(task)) == files
    importlib.import_module("labtask.extra")
    assert list(stages_module._user_sources(task)) == files
    monkeypatch.setattr(site, "getsitepackages", lambda: [str(tmp_path)])  # installed there
    assert list(stages_module._user_sources(task)) == files[1:]


def test_a_resuming_run_says_what_it_read(tmp_path):
    assert format_resumed({}) == []
    assert format_resumed({"resumed": ["fit_map"]}) == [
        "resumed: fit_map read from the earlier run"
    ]
    assert "every fit ran anew" in format_resumed({"resumed": []})[0]


def _strip(summary: dict) -> dict:
    """A summary without what differs between two runs of the same numbers: wall times."""
    summary = json.loads(json.dumps(summary))
    summary.pop("timings")
    summary.pop("resumed", None)
    for entry in summary.get("methods", {}).values():
        entry.pop("fit_s", None)
    return summary


def _without_figures(monkeypatch) -> None:
    """Runs that draw no figures: these tests compare the numbers a resumed run writes, and
    drawing is a fifth of a small run's time (a resumed fit's figures are drawn below, a
    whole run's in test_fit2d and test_cli_fit)."""
    monkeypatch.setattr(recover2d, "plot_recovery", lambda summary, path, **kwargs: Path(path))
    monkeypatch.setattr(recover2d, "belief_figures", lambda *args, **kwargs: [])
    monkeypatch.setattr(recordings, "report_run", lambda folder: [])


@pytest.fixture
def no_figures(monkeypatch):
    """:func:`_without_figures` for the whole test."""
    _without_figures(monkeypatch)


def _stop_at_call(monkeypatch, module, name: str, n: int) -> list[int]:
    """Count the calls of ``module.name`` from now on, stopping the run at the ``n``-th."""
    work, calls = getattr(module, name), []

    def stop(*args, **kwargs):
        calls.append(1)
        if len(calls) == n:
            raise Interrupted
        return work(*args, **kwargs)

    monkeypatch.setattr(module, name, stop)
    return calls


def _count_fits(monkeypatch, module) -> list[str]:
    """The methods of the fits ``module`` runs from now on."""
    fit, methods = module.fit_theta, []

    def counted(loss, *args, **kwargs):
        methods.append(loss.method)
        return fit(loss, *args, **kwargs)

    monkeypatch.setattr(module, "fit_theta", counted)
    return methods


def test_an_interrupted_recovery_resumes_to_the_uninterrupted_numbers(
    tmp_path, monkeypatch, no_figures
):
    """Stopped while simulating its second calibration dataset, a recovery resumed fits only
    that dataset and ends with the summary and trials of one never stopped; rerun with a third
    dataset, it fits only the third."""
    config = Recovery2DConfig(**TINY)
    whole = run_recovery(config, tmp_path / "whole", show_progress=False)
    with monkeypatch.context() as patch:
        _stop_at_call(patch, recover2d, "simulate_at_fits", 2)
        with pytest.raises(Interrupted):
            run_recovery(config, tmp_path / "run", show_progress=False)
    assert not (tmp_path / "run" / "summary.json").exists()
    fits = _count_fits(monkeypatch, recover2d)
    resumed = run_recovery(config, tmp_path / "run", show_progress=False, resume=True)
    assert fits == ["map", "marginal"]
    assert resumed["resumed"] == ["fit_map", "fit_marginal", "calibration1_map",
                                  "calibration1_marginal"]  # fmt: skip
    assert _strip(resumed) == _strip(whole)
    run, reference = (TensorDict.load_memmap(tmp_path / d / "trials") for d in ("run", "whole"))
    assert (run == reference).all()
    more = Recovery2DConfig(**{**TINY, "calibrate": 3})
    extended = run_recovery(more, tmp_path / "run", show_progress=False, resume=True)
    assert fits == ["map", "marginal"] * 2
    assert extended["methods"]["marginal"]["calibrated"]["n_datasets"] == 3
    stages = sorted(p.stem for p in (tmp_path / "run" / "stages").glob("*.pt"))
    names = ("fit", "calibration1", "calibration2", "calibration3")
    assert stages == sorted(f"{s}_{m}" for s in names for m in ("map", "marginal"))
    assert staged_by(tmp_path / "run" / "stages") == "recover"  # another command refuses them


def test_a_recovery_of_other_settings_refits_and_leaves_only_its_own_stages(tmp_path, monkeypatch):
    """Every fit replaced by a fixed result: another seed keys other stages, so resuming fits
    all again, and the earlier run's stages beyond this run's (a third dataset) are removed."""
    methods = []

    def fit(loss, held, **kwargs):
        methods.append(loss.method)
        return _result(len(methods), held.shape[0])

    monkeypatch.setattr(recover2d, "fit_theta", fit)
    monkeypatch.setattr(recover2d, "_truth_check", lambda *args: {})
    monkeypatch.setattr(recover2d, "write_recovery", lambda *args: None)
    first = Recovery2DConfig(**{**TINY, "calibrate": 3})
    run_recovery(first, tmp_path, show_progress=False)
    assert len(methods) == 8
    second = Recovery2DConfig(**{**TINY, "seed": 1})
    assert recovery_stages(second, tmp_path).key != recovery_stages(first, tmp_path).key
    summary = run_recovery(second, tmp_path, show_progress=False, resume=True)
    assert len(methods) == 14 and summary["resumed"] == []
    assert sorted(p.stem for p in (tmp_path / "stages").glob("*.pt")) == sorted(
        f"{s}_{m}" for s in ("fit", "calibration1", "calibration2") for m in ("map", "marginal")
    )
    resumed = run_recovery(second, tmp_path, show_progress=False, resume=True)
    assert len(methods) == 14 and len(resumed["resumed"]) == 6
    # the same settings, but trials simulated otherwise (a task changed where no key reads)
    simulate = recover2d.simulate_recovery_agents

    def changed(*args, **kwargs):
        trials, theta, mistaken = simulate(*args, **kwargs)
        trials["action"] = trials["action"] * 0.5
        return trials, theta, mistaken

    monkeypatch.setattr(recover2d, "simulate_recovery_agents", changed)
    again = run_recovery(second, tmp_path, show_progress=False, resume=True)
    assert len(methods) == 20 and again["resumed"] == []


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> list[Path]:
    """Three simulated agents of 4 trials each, as CSV recordings."""
    out = tmp_path_factory.mktemp("recorded")
    assert main(["simulate", "--out", str(out), "--quiet", "n_agents=3", "n_trials=4",
                 "threads=1"]) == 0  # fmt: skip
    return sorted(out.glob("agent*.csv"))


def test_an_interrupted_fit_of_recordings_resumes_from_the_command_line(
    recorded, tmp_path, monkeypatch, capsys, no_figures
):
    """``irc fit --resume`` after a fit stopped in its second calibration dataset refits only
    that dataset, says what it read, and writes the summary of a fit never stopped."""
    files = [str(p) for p in recorded]
    settings = ["n_screen=2", "n_starts=1", "max_iter=2", "curvature=bfgs", "calibrate=2",
                "threads=1"]  # fmt: skip
    whole = RecordingFitConfig(
        n_screen=2, n_starts=1, max_iter=2, curvature="bfgs", calibrate=2, threads=1
    )
    recordings.fit_recordings(files, tmp_path / "whole", whole, progress=False)
    out = str(tmp_path / "run")
    with monkeypatch.context() as patch:
        _stop_at_call(patch, recordings, "simulate_at_fits", 2)
        with pytest.raises(Interrupted):
            main(["fit", *files, "--out", out, "--quiet", *settings])
    fits = _count_fits(monkeypatch, recordings)
    assert main(["fit", *files, "--out", out, "--quiet", "--resume", *settings]) == 0
    assert fits == ["map", "marginal"]
    printed = capsys.readouterr().out
    assert (
        "resumed: fit_4trials_map, fit_4trials_marginal, calibration1atmarginal_4trials_map"
        in printed
    )
    summary, reference = (json.loads((tmp_path / d / "summary.json").read_text()) for d in
                          ("run", "whole"))  # fmt: skip
    assert _strip(summary) == _strip(reference)


def test_a_recovery_stopped_in_its_particle_checks_resumes_with_those_done(
    tmp_path, monkeypatch, no_figures
):
    """Killed in its third particle check (marginal's at θ̂), a recovery resumed reads both
    fits and map's two checks (with their times) and runs only marginal's, to the numbers of
    a run never stopped."""
    config = Recovery2DConfig(**{**TINY, "calibrate": 0, "particles": 16})
    whole = run_recovery(config, tmp_path / "whole", show_progress=False)
    with monkeypatch.context() as patch:
        _stop_at_call(patch, recover2d, "particle_check", 3)
        with pytest.raises(Interrupted):
            run_recovery(config, tmp_path / "run", show_progress=False)
    calls = _stop_at_call(monkeypatch, recover2d, "particle_check", 0)
    resumed = run_recovery(config, tmp_path / "run", show_progress=False, resume=True)
    assert len(calls) == 2 and resumed["resumed"] == [
        "fit_map", "fit_marginal", "particles16_at_theta_hat_map", "particles16_at_theta_true_map"
    ]  # fmt: skip
    assert _strip(resumed) == _strip(whole)
    folder = tmp_path / "run" / "stages"
    kept = [folder / f"particles16_{w}_map.pt" for w in ("at_theta_hat", "at_theta_true")]
    seconds = sum(read_weights(path)["seconds"] for path in kept)  # the earlier run's time
    assert resumed["timings"]["particle_check_map_s"] == seconds


def test_a_fit_of_recordings_resumed_reads_its_particle_checks(recorded, tmp_path, monkeypatch):
    """Rerun with ``--resume``, a finished fit with particle checks reads every fit and check
    and draws its figures from what it read; with another particle count it runs only the
    checks."""
    config = RecordingFitConfig(n_screen=2, n_starts=1, max_iter=2, particles=16, threads=1)
    files = [str(p) for p in recorded]
    with monkeypatch.context() as patch:
        _without_figures(patch)
        whole = recordings.fit_recordings(files, tmp_path, config, progress=False)
    assert not list(tmp_path.glob("*.png"))
    fits = _count_fits(monkeypatch, recordings)
    checks = _stop_at_call(monkeypatch, recordings, "particle_check", 0)
    again = recordings.fit_recordings(files, tmp_path, config, progress=False, resume=True)
    assert fits == [] and checks == [] and again["resumed"] == [
        "fit_4trials_map", "fit_4trials_marginal", "particles16_4trials_marginal"
    ]  # fmt: skip
    assert _strip(again) == _strip(whole)
    drawn = [f"agent{i}_beliefs_{view}.png" for i in range(3) for view in ("overhead", "time")]
    assert sorted(p.name for p in tmp_path.glob("*.png")) == [
        *drawn,
        "q_function.png",
        "recovery.png",
    ]
    more = dataclasses.replace(config, particles=24)
    with monkeypatch.context() as patch:
        _without_figures(patch)
        recordings.fit_recordings(files, tmp_path, more, progress=False, resume=True)
    assert fits == [] and len(checks) == 1
