"""Checkpoints: weights-only round trips, clear errors, and resuming a killed run."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import default_dtype

import irc_torchrl
from irc_torchrl.algorithms.ensemble import (
    RESUME_ENTRIES,
    Firefly2DConfig,
    load_ensemble_critic,
    load_ensemble_policy,
    make_model,
    train_ensemble,
)
from irc_torchrl.checkpoint import load_checkpoint, save_checkpoint
from irc_torchrl.config import load_firefly2d_config
from irc_torchrl.envs.firefly2d import firefly2d_theta_space

_SPACE = firefly2d_theta_space()

TINY = [
    "ddpg.n_envs=32",
    "ddpg.steps_per_batch=2",
    "ddpg.updates_per_batch=2",
    "ddpg.total_frames=1280",
    "ddpg.warmup_frames=256",
    "ddpg.clone_updates=10",
    "ddpg.critic_updates=10",
    "ddpg.batch_size=64",
    "ddpg.hidden=[16, 16]",
    "evaluation.n_theta=4",
    "evaluation.trials_per_theta=2",
    "evaluation.every=10",
    "checkpoint_every=10",
    "logger=none",
]


def tiny(*extra: str) -> Firefly2DConfig:
    return load_firefly2d_config(overrides=[*TINY, *extra])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    return train_ensemble(tiny(), out=out, progress=False), out


def test_round_trip_restores_weights_and_counters(trained):
    result, out = trained
    ckpt = load_checkpoint(
        out / "checkpoint.pt", task="firefly2d", theta_space=result.model.theta_space
    )
    assert ckpt["counters"] == {
        "frames": result.frames,
        "updates": result.updates,
        "warmup_frames": 256,  # the pursuit warm-up's, on top of total_frames
    }
    assert ckpt["version"] == irc_torchrl.__version__
    assert ckpt["config"]["ddpg"]["hidden"] == [16, 16]
    for name, value in result.actor.state_dict().items():
        assert torch.equal(ckpt["best_actor"][name], value)
    assert isinstance(ckpt["rng"]["torch"], torch.Tensor)


def test_a_checkpoint_trained_on_a_gpu_loads_and_resumes_on_the_cpu(
    trained, tmp_path, monkeypatch
):
    """A GPU run's file (its tensors tagged cuda:0, the GPU's random state, its config naming a
    device this machine lacks) loads here, and a resume continues on the config's device."""
    result, out = trained
    ckpt = load_checkpoint(out / "checkpoint.pt", task="firefly2d")
    kept = ("format", "task", "version", "theta_space", "config", "path")
    state = {k: v for k, v in ckpt.items() if k not in kept}
    state["rng"] = {**state["rng"], "cuda": torch.zeros(16, dtype=torch.uint8)}
    with monkeypatch.context() as patch:  # torch.save tags each tensor with its device
        patch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
        path = save_checkpoint(
            tmp_path / "gpu.pt",
            task="firefly2d",
            theta_space=result.model.theta_space,
            config={**ckpt["config"], "device": "cuda:0"},
            state=state,
        )
    if not torch.cuda.is_available():  # the tags are real: torch alone would want the GPU
        with pytest.raises(RuntimeError):
            torch.load(path, weights_only=True)
    actor, _, _ = load_ensemble_policy(path)
    critic, _, _ = load_ensemble_critic(path)
    for name, value in result.actor.state_dict().items():
        assert torch.equal(actor.state_dict()[name], value)
    assert next(critic.parameters()).device.type == "cpu"
    with pytest.warns(UserWarning, match="was trained on cuda:0; continuing on cpu"):
        resumed = train_ensemble(tiny(), resume=path, progress=False)
    assert resumed.updates == result.updates


def test_mismatched_task_and_theta_space_are_clear_errors(trained):
    _, out = trained
    with pytest.raises(ValueError, match="task is 'firefly2d', expected 'firefly1d'"):
        load_checkpoint(out / "checkpoint.pt", task="firefly1d")
    other = firefly2d_theta_space().with_range("g_v", 0.5, 2.0)
    with pytest.raises(ValueError, match="theta_space is ThetaSpace"):
        load_checkpoint(out / "checkpoint.pt", theta_space=other)
    with pytest.raises(ValueError, match="theta_space"):
        train_ensemble(tiny("theta_fixed={g_v: 1.0}"), resume=out / "checkpoint.pt", progress=False)


@pytest.mark.parametrize(
    "override, message",
    [
        ("ddpg.hidden=[32]", r"has ddpg.hidden=\[16, 16\], the config \[32\]"),
        ("ddpg.loss=td3", "has ddpg.loss='ddpg', the config 'td3'"),
        ("ddpg.activation=relu", "has ddpg.activation='softplus', the config 'relu'"),
    ],
)
def test_resuming_with_other_networks_names_the_setting(tmp_path, trained, override, message):
    _, out = trained
    with pytest.raises(ValueError, match=f"resume: checkpoint .*{message}"):
        train_ensemble(tiny(override), out=tmp_path, resume=out / "checkpoint.pt", progress=False)
    assert list(tmp_path.iterdir()) == []  # refused before writing anything


def test_missing_truncated_and_pickled_files_are_refused(tmp_path, trained):
    _, out = trained
    with pytest.raises(FileNotFoundError, match="absent.pt"):
        load_checkpoint(tmp_path / "absent.pt")
    with pytest.raises(FileNotFoundError, match="no packaged checkpoint named 'nope'"):
        load_checkpoint("nope")
    data = (out / "checkpoint.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="not a readable irc_torchrl checkpoint"):
        load_checkpoint(tmp_path / "cut.pt")
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(ValueError, match="checkpoint"):
        load_checkpoint(tmp_path / "garbage.pt")
    torch.save({"format": "irc_torchrl.checkpoint/1", "evil": _Exploit()}, tmp_path / "evil.pt")
    with pytest.raises(ValueError, match="refused to load"):
        load_checkpoint(tmp_path / "evil.pt")
    assert not _Exploit.ran


def test_damaged_archive_and_text_file_are_refused(tmp_path, trained):
    """torch reads a tensor whose bytes were overwritten without complaint; the CRCs catch it."""
    _, out = trained
    data = bytearray((out / "checkpoint.pt").read_bytes())
    with zipfile.ZipFile(out / "checkpoint.pt") as archive:
        tensors = [info for info in archive.infolist() if "/data/" in info.filename]
        largest = max(tensors, key=lambda info: info.file_size)
    middle = largest.header_offset + 128 + largest.file_size // 2  # inside its bytes
    data[middle : middle + 16] = bytes(255 - b for b in data[middle : middle + 16])
    (tmp_path / "damaged.pt").write_bytes(data)
    for load in (load_checkpoint, load_ensemble_policy, load_ensemble_critic):
        with pytest.raises(ValueError, match=r"damaged.pt: not a readable .* fails its CRC check"):
            load(tmp_path / "damaged.pt")
    (tmp_path / "text.pt").write_text("hello")  # torch.load raises KeyError: 101
    with pytest.raises(ValueError, match=r"text.pt: not a readable .*; expected a file written"):
        load_checkpoint(tmp_path / "text.pt")


def _edited(trained, tmp_path, edit) -> str:
    """The trained checkpoint with its payload changed by ``edit``, saved with valid CRCs."""
    _, out = trained
    payload = torch.load(out / "checkpoint.pt", weights_only=True)
    edit(payload)
    torch.save(payload, tmp_path / "edited.pt")
    return str(tmp_path / "edited.pt")


def test_non_finite_weights_are_refused_naming_the_entry(tmp_path, trained):
    name = next(iter(trained[0].actor.state_dict()))
    path = _edited(trained, tmp_path, lambda p: p["best_actor"][name].view(-1)[0].fill_(torch.nan))
    with pytest.raises(ValueError, match=f"edited.pt: entry best_actor/{name} holds NaN"):
        load_checkpoint(path)


def test_missing_entries_are_named(tmp_path, trained):
    path = _edited(trained, tmp_path, lambda p: p.pop("version"))
    with pytest.raises(ValueError, match=r"edited.pt: missing entries \['version'\]"):
        load_checkpoint(path)
    path = _edited(trained, tmp_path, lambda p: p.pop("best_actor"))
    load_ensemble_critic(path)  # the critic does not need the kept policy
    with pytest.raises(ValueError, match=r"missing entries \['best_actor'\]"):
        load_ensemble_policy(path)
    with pytest.raises(ValueError, match=r"missing entries \['best_actor'\]"):
        train_ensemble(tiny(), out=tmp_path / "run", resume=path, progress=False)


def test_a_config_or_theta_space_that_is_not_irc_trains_is_refused(tmp_path, trained):
    def listed(payload):
        payload["config"] = list(payload["config"].items())

    with pytest.raises(ValueError, match=r"edited.pt: entry config is a list; expected a mapping"):
        load_checkpoint(_edited(trained, tmp_path, listed))

    def mangled(payload):
        payload["config"]["ddpg"]["gamma"] = 7.0

    with pytest.raises(
        ValueError, match=r"edited.pt: entry config is not a config irc train writes .*ddpg.gamma"
    ):
        load_ensemble_policy(_edited(trained, tmp_path, mangled))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda ts: ts.pop("parameters"), r"expected \{'parameters'"),
        (lambda ts: ts["parameters"][0].update(foo=1), "parameter entry 'g_v': unknown key 'foo'"),
        (lambda ts: ts["parameters"][0].update(low="a"), "'g_v': low: expected a real"),
        (lambda ts: ts.update(fixed={"zz": 1.0}), "unknown θ parameter 'zz'"),
    ],
)
def test_a_malformed_theta_space_is_refused_naming_the_file(tmp_path, trained, edit, message):
    """It raised KeyError 'parameters', TypeError or a comparison error from deep inside."""
    path = _edited(trained, tmp_path, lambda p: edit(p["theta_space"]))
    pattern = f"^checkpoint .*edited.pt: entry theta_space: (parameter )?{message}"
    for load in (load_checkpoint, load_ensemble_policy, load_ensemble_critic):
        with pytest.raises(ValueError, match=pattern):
            load(path)


@pytest.mark.parametrize(
    "state, message",
    [
        ({"task": "other", "format": "x"}, r"state entries \['format', 'task'\] are reserved"),
        ({"path": "x"}, r"state entries \['path'\] are reserved"),
        ({"x": object()}, "state/x is a builtins.object"),
        ({"rng": {"numpy": [np.float32(1.0)]}}, "state/rng/numpy/0 is a numpy.float32"),
        ({"x": {frozenset(): 1}}, "state/x has a key frozenset"),
        ({"opt": [torch.ones(2), torch.tensor([0.0, torch.nan])]}, "state entry opt/1 holds NaN"),
    ],
)
def test_saving_refuses_what_loading_would_refuse(tmp_path, state, message):
    """The state overwrote the header or held objects a weights-only load refuses: the file
    was written, and refused (or read as another task's) later."""
    with pytest.raises(ValueError, match=f"^save_checkpoint: {message}"):
        save_checkpoint(
            tmp_path / "c.pt", task="firefly2d", theta_space=_SPACE, config={}, state=state
        )
    with pytest.raises(ValueError, match="^save_checkpoint: config/seed is a numpy.int64"):
        save_checkpoint(
            tmp_path / "c.pt",
            task="firefly2d",
            theta_space=_SPACE,
            config={"seed": np.int64(1)},
            state={},
        )
    assert list(tmp_path.iterdir()) == []  # refused before writing anything


def test_saving_keeps_plain_state_and_refuses_bad_arguments(tmp_path):
    state = {"w": torch.ones(2), "opt": {0: {"step": 1}}, "groups": [{"betas": (0.9, 0.99)}]}
    path = save_checkpoint(
        tmp_path / "c.pt", task="firefly2d", theta_space=_SPACE, config={}, state=state
    )
    ckpt = load_checkpoint(path, task="firefly2d", theta_space=_SPACE, required="opt")
    assert ckpt["opt"] == {0: {"step": 1}} and ckpt["groups"] == [{"betas": (0.9, 0.99)}]
    with pytest.raises(ValueError, match="task must be a non-empty string"):
        save_checkpoint(tmp_path / "d.pt", task=3, theta_space=_SPACE, config={}, state={})
    with pytest.raises(ValueError, match="theta_space must be a ThetaSpace"):
        save_checkpoint(tmp_path / "d.pt", task="firefly2d", theta_space={}, config={}, state={})
    with pytest.raises(ValueError, match="state must be a mapping"):
        save_checkpoint(
            tmp_path / "d.pt", task="firefly2d", theta_space=_SPACE, config={}, state=[1]
        )
    assert not (tmp_path / "d.pt").exists()


@pytest.mark.parametrize("entry", ["best_actor", "actor", "loss"])
def test_weights_that_do_not_fit_their_config_are_refused(tmp_path, trained, entry):
    def shrink(payload):
        # in the loss, a critic weight (load_ensemble_critic reads those); one row, which
        # TorchRL's loss would broadcast over the whole matrix without a word
        name = next(k for k in payload[entry] if k.endswith("weight") and "actor" not in k)
        payload[entry][name] = payload[entry][name][:1]

    path = _edited(trained, tmp_path, shrink)
    load = load_ensemble_policy if entry == "best_actor" else load_ensemble_critic
    message = rf"edited.pt: entry {entry} does not fit the networks its config builds \(.* is \[1,"
    with pytest.raises(ValueError, match=message):
        load(path)
    if entry != "actor":  # a resumed run reads the loss's actor, not this copy
        with pytest.raises(ValueError, match=message):
            train_ensemble(tiny(), out=tmp_path / "run", resume=path, progress=False)
        assert not (tmp_path / "run").exists()  # refused before writing anything


def test_missing_weights_are_refused_on_resume(tmp_path, trained):
    """TorchRL's loss would load without them, keeping the fresh initialisation."""
    path = _edited(trained, tmp_path, lambda p: p["loss"].pop(next(iter(p["loss"]))))
    with pytest.raises(ValueError, match=r"entry loss does not fit .*\(1 weight\(s\) missing"):
        train_ensemble(tiny(), out=tmp_path / "run", resume=path, progress=False)


def test_other_major_version_is_refused(tmp_path):
    space = make_model(Firefly2DConfig()).theta_space
    path = save_checkpoint(
        tmp_path / "c.pt", task="firefly2d", theta_space=space, config={}, state={}
    )
    payload = torch.load(path, weights_only=True)
    payload["version"] = "99.0.0"
    torch.save(payload, path)
    with pytest.raises(ValueError, match="version 99.0.0"):
        load_checkpoint(path)


def test_another_minor_version_of_the_same_major_loads(tmp_path):
    """Only the major version is compared: a checkpoint from 0.99.0 loads under 0.1.0."""
    path = save_checkpoint(
        tmp_path / "c.pt", task="firefly2d", theta_space=_SPACE, config={}, state={}
    )
    payload = torch.load(path, weights_only=True)
    payload["version"] = f"{irc_torchrl.__version__.split('.')[0]}.99.0"
    torch.save(payload, path)
    assert load_checkpoint(path, task="firefly2d", theta_space=_SPACE)["version"].endswith(".99.0")


@pytest.mark.parametrize("value", [torch.inf, -torch.inf, torch.nan])
def test_a_non_finite_tensor_inside_a_list_is_refused_naming_it(tmp_path, value):
    """An optimiser's state holds lists of tensors; an infinite one is as damaged as a NaN,
    whether saving meets it (diverged training) or loading (a file edited or damaged since)."""
    state = {"opt": {"groups": [torch.ones(2), torch.tensor([1.0, value])]}}
    with pytest.raises(ValueError, match="save_checkpoint: state entry opt/groups/1 holds NaN"):
        save_checkpoint(
            tmp_path / "c.pt", task="firefly2d", theta_space=_SPACE, config={}, state=state
        )
    path = save_checkpoint(
        tmp_path / "c.pt", task="firefly2d", theta_space=_SPACE, config={}, state={}
    )
    payload = torch.load(path, weights_only=True)
    torch.save({**payload, **state}, path)
    with pytest.raises(ValueError, match="c.pt: entry opt/groups/1 holds NaN or infinite"):
        load_checkpoint(path)


def test_a_failing_save_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    """A run killed while saving leaves the last good checkpoint and no partial file beside it;
    a full disk is the OSError it is (torch's own writer raised a RuntimeError of its C++
    stream, which irc printed as a traceback)."""
    path = save_checkpoint(
        tmp_path / "c.pt", task="firefly2d", theta_space=_SPACE, config={}, state={"n": 1}
    )
    good = path.read_bytes()

    def disk_full(self, data):
        with open(self, "wb") as file:
            file.write(bytes(data)[:10])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", disk_full)
    with pytest.raises(OSError, match="No space left on device"):
        save_checkpoint(path, task="firefly2d", theta_space=_SPACE, config={}, state={"n": 2})
    monkeypatch.undo()
    assert path.read_bytes() == good and list(tmp_path.iterdir()) == [path]
    assert load_checkpoint(path)["n"] == 1


def test_a_fresh_run_into_an_earlier_runs_folder_leaves_no_mixture(tmp_path, monkeypatch):
    """A rerun into the same --out appended its log rows to the earlier run's (34 lines became
    68), and one interrupted after its first checkpoint left the earlier run's summary beside
    its own checkpoint and config. Logs start afresh; config.yaml goes with each checkpoint and
    the earlier summary with the checkpoint it described."""
    out = tmp_path / "run"
    csv = [o for o in TINY if not o.startswith("logger=")] + ["logger=csv"]
    train_ensemble(load_firefly2d_config(overrides=csv), out=out, progress=False)

    def rows() -> dict[str, int]:
        return {p.name: len(p.read_text().splitlines()) for p in out.glob("logs/*/scalars/*")}

    first = rows()
    assert first and (out / "summary.json").is_file()
    (out / "logs" / "mine.txt").write_text("a file of the user's own, beside the logger's")
    train_ensemble(load_firefly2d_config(overrides=[*csv, "seed=5"]), out=out, progress=False)
    assert rows() == first and (out / "logs" / "mine.txt").is_file()
    calls = []

    def interrupted_after_the_first(*args, **kwargs):
        calls.append(1)
        if len(calls) > 1:
            raise KeyboardInterrupt
        return save_checkpoint(*args, **kwargs)

    monkeypatch.setattr(
        "irc_torchrl.algorithms.ensemble.save_checkpoint", interrupted_after_the_first
    )
    with pytest.raises(KeyboardInterrupt):
        train_ensemble(load_firefly2d_config(overrides=[*csv, "seed=6"]), out=out, progress=False)
    assert yaml.safe_load((out / "config.yaml").read_text())["seed"] == 6
    assert load_checkpoint(out / "checkpoint.pt")["config"]["seed"] == 6
    assert not (out / "summary.json").exists()


def test_resume_restores_state_and_is_deterministic(tmp_path, trained):
    """Resuming is deterministic and restores everything saved.

    It cannot equal an uninterrupted run bit for bit: the replay buffer and the trials in flight
    are deliberately not checkpointed (the issue asks for a replay-free state), so a resumed run
    refills its buffer with the current policy. The honest properties are tested instead.
    """
    first = train_ensemble(tiny("ddpg.total_frames=640"), out=tmp_path / "a", progress=False)
    ckpt = tmp_path / "a" / "checkpoint.pt"
    runs = [
        train_ensemble(
            tiny("ddpg.total_frames=1920"), out=tmp_path / name, resume=ckpt, progress=False
        )
        for name in "bc"
    ]
    assert runs[0].frames == runs[1].frames >= 1920
    assert runs[0].updates > first.updates
    for name, value in runs[0].critic.state_dict().items():
        assert torch.equal(value, runs[1].critic.state_dict()[name])
    # the resumed run started from the saved weights, not from a fresh initialisation
    assert runs[0].history[: len(first.history)] == first.history


def test_a_resumed_run_ends_at_the_frames_of_an_uninterrupted_one(tmp_path, trained):
    """``total_frames`` counts the exploring policy's frames, the pursuit warm-up's come on
    top: a resumed run counted the warm-up's against its budget too, and stopped short of the
    uninterrupted run (here without a single update after the resume)."""
    result, _ = trained
    first = train_ensemble(tiny("ddpg.total_frames=640"), out=tmp_path, progress=False)
    resumed = train_ensemble(tiny(), resume=tmp_path / "checkpoint.pt", progress=False)
    assert resumed.frames == result.frames == 1280 + 256
    assert resumed.updates > first.updates


class _Exploit:
    ran = False

    def __reduce__(self):
        return (_Exploit._run, ())

    @staticmethod
    def _run():
        _Exploit.ran = True
        return "pwned"


def _same(a, b) -> bool:
    """Equal nested state: dicts, lists and tuples of tensors (bit for bit) and plain values."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    return a == b


def test_resuming_a_finished_run_restores_every_entry_it_reads(tmp_path, trained):
    """With nothing left to train (it warns), a resumed run checkpoints what it restored:
    networks and their targets, optimisers, the annealed noise, the kept policy, counters and
    history; its random stream goes on from the saved one (setting the run up draws from
    it)."""
    _, out = trained
    before = torch.load(out / "checkpoint.pt", weights_only=True)
    seed99 = torch.Generator().manual_seed(99).get_state()
    other = _edited(trained, tmp_path, lambda p: p["rng"].update(torch=seed99))
    after = {}
    for name, path in (("same", out / "checkpoint.pt"), ("other", other)):
        with pytest.warns(UserWarning, match="trained 1280 frames, .* 1280: nothing left to train"):
            train_ensemble(tiny(), out=tmp_path / name, resume=path, progress=False)
        after[name] = torch.load(tmp_path / name / "checkpoint.pt", weights_only=True)
    for entry in (*RESUME_ENTRIES, "actor"):
        if entry != "rng":
            assert _same(before[entry], after["same"][entry]), entry
    assert not torch.equal(after["same"]["rng"]["torch"], after["other"]["rng"]["torch"])


def test_a_resumed_run_runs_its_own_configs_rates_and_noise_saying_what_changed(
    tmp_path, trained
):
    """The restored optimisers and noise carried the checkpoint's rates and noise bounds: a
    config resumed with other ones wrote them to config.yaml but trained with the old."""
    _, out = trained
    changed = ["ddpg.lr_actor=3e-4", "ddpg.lr_critic=2e-3", "ddpg.sigma_end=0.01"]
    with pytest.warns(UserWarning, match=r"ddpg.lr_actor: 0.0001 → 0.0003; ddpg.lr_critic"):
        train_ensemble(
            tiny("ddpg.total_frames=1536", *changed),
            out=tmp_path,
            resume=out / "checkpoint.pt",
            progress=False,
        )
    ckpt = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    rates = [ckpt[f"optimiser_{n}"]["param_groups"][0]["lr"] for n in ("actor", "critic")]
    assert rates == [3e-4, 2e-3]
    assert ckpt["exploration"]["sigma_end"].item() == pytest.approx(0.01)
    assert ckpt["exploration"]["sigma_init"].item() == pytest.approx(0.15)


def test_irc_train_resumed_goes_on_with_the_checkpoints_settings(tmp_path, trained, recwarn):
    """irc train --resume rebuilt its config from the defaults: a run over 32 envs, [16, 16]
    networks and a 4-θ grid was refused, or where the networks matched went on over 64 envs
    and another grid (the kept policy chosen on two grids), without a word. Now the
    checkpoint's settings go on, and a setting changed on resuming is named."""
    from irc_torchrl.cli import main

    _, out = trained
    resume = ["train", "--resume", str(out / "checkpoint.pt"), "--quiet", "ddpg.total_frames=1536"]
    assert main([*resume, "--out", str(tmp_path / "a")]) == 0
    assert not recwarn.list  # a larger budget is why one resumes
    config = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())
    ddpg = config["ddpg"]
    assert (ddpg["n_envs"], ddpg["hidden"], ddpg["total_frames"]) == (32, [16, 16], 1536)
    assert (config["evaluation"]["n_theta"], config["logger"]) == (4, "none")
    changed = rf"^resume: continuing {out / 'checkpoint.pt'} with the config's evaluation.n_t"
    with pytest.warns(UserWarning, match=changed + r"heta: 4 → 8$"):
        assert main([*resume, "--out", str(tmp_path / "b"), "evaluation.n_theta=8"]) == 0
    # not its device: a GPU's run goes on on this machine's (saying so), as the library's does
    gpu = _edited(trained, tmp_path, lambda p: p["config"].update(device="cuda:0"))
    resume[2] = gpu
    with pytest.warns(UserWarning, match="was trained on cuda:0; continuing on cpu"):
        assert main([*resume, "--out", str(tmp_path / "c")]) == 0


def test_checkpoints_fall_at_batch_ends_so_a_resume_misses_no_update(tmp_path, monkeypatch):
    """With 2 updates per batch and a checkpoint every 3 updates, the checkpoint waits for the
    batch's end (updates 4, 6, 10, 12): written mid-batch (update 3), it counted the whole
    batch's frames with half its updates, and a run resumed from it skipped the rest."""
    from irc_torchrl.algorithms import ensemble

    saved, save = [], ensemble.save_checkpoint

    def spy(path, **kwargs):
        saved.append(dict(kwargs["state"]["counters"]))
        return save(path, **kwargs)

    monkeypatch.setattr(ensemble, "save_checkpoint", spy)
    config = tiny("checkpoint_every=3", "ddpg.total_frames=640")
    train_ensemble(config, out=tmp_path, progress=False)
    assert [s["updates"] for s in saved] == [4, 6, 10, 12, 12]  # the last one: the run's end
    # updates begin once the n-step buffer holds warmup_frames (at 512 frames here); from then
    # every 64 frames bring 2 updates, none of them left for a resume to make
    assert all(s["frames"] == 512 + 32 * s["updates"] for s in saved)


def test_training_under_a_float64_default_dtype_trains_the_same_float32_networks(tmp_path, trained):
    """TorchRL's noise module draws in the default dtype: under float64 the run failed (float64
    actions into the float32 critic); it runs in float32 and restores the caller's default."""
    result, _ = trained
    with default_dtype(torch.float64):
        again = train_ensemble(tiny(), out=tmp_path, progress=False)
        assert torch.get_default_dtype() == torch.float64
    for name, value in result.actor.state_dict().items():
        assert torch.equal(again.actor.state_dict()[name], value), name
