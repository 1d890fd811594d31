"""The trainer on a toy model and toy data: loss goes down, every term has gradients, checkpoints
resume bit-exactly, the run folder has what it promises."""

from __future__ import annotations

import csv

import pytest
import torch

from fastgha_core.model.fastgha import FastGHA
from fastgha_core.train.losses import LOSS_TERMS
from fastgha_core.train.toy import ToyDataset, collate_toy, toy_model_config
from fastgha_core.train.trainer import DistInfo, StreamSampler, TrainConfig, Trainer, latest_checkpoint, load_train_config


@pytest.fixture(scope="module")
def toy_data():
    return ToyDataset(length=16, size=32, seed=0)


def _trainer(run_dir, data, seed=0, init_seed=None, **kw):
    opts = dict(model="toy", lr=2e-3, lr_deform=2e-3, val_every=0, ckpt_every=0, log_every=1, render_backend="cpu", seed=seed)
    cfg = TrainConfig(**{**opts, **kw})
    torch.manual_seed(seed if init_seed is None else init_seed)
    model = FastGHA(toy_model_config(32))
    return Trainer(cfg, model, data, run_dir, dist=DistInfo(), collate_fn=collate_toy)


def test_training_reduces_loss_on_a_batch_and_every_term_has_gradients(tmp_path, toy_data):
    tr = _trainer(tmp_path, toy_data)
    batch = collate_toy([toy_data[0]])
    terms, _ = tr.compute_losses(batch)
    params = [p for p in tr.model.parameters() if p.requires_grad]
    for name in ("rgb", "ssim", "sil", "geo"):
        assert torch.isfinite(terms[name]), name
        grads = torch.autograd.grad(terms[name], params, retain_graph=True, allow_unused=True)
        assert any(g is not None and g.abs().sum() > 0 for g in grads), f"{name} has no gradient"
        assert all(g is None or torch.isfinite(g).all() for g in grads), name
    before = float(terms["total"].detach())
    for _ in range(6):
        tr.train_step(batch)
    with torch.no_grad():
        after = float(tr.compute_losses(batch)[0]["total"])
    assert after < before - 0.02, (before, after)


def test_resume_is_bit_exact(tmp_path, toy_data):
    # the single run also writes checkpoints every step and a validation grid: neither may perturb training
    one = _trainer(tmp_path / "one", toy_data, warmup_steps=2, ckpt_every=1, keep_checkpoints=2, val_every=2, val_samples=1)
    one.fit(steps=3)
    split = _trainer(tmp_path / "split", toy_data, warmup_steps=2)
    split.fit(steps=2)
    # a new process rebuilds the model from scratch: start from different weights on purpose
    resumed = _trainer(tmp_path / "split", toy_data, init_seed=123, warmup_steps=2)
    resumed.fit(steps=3, resume=True)
    assert resumed.step == 3
    for (name, a), (_, b) in zip(one.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name
    sa, sb = one.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k]["exp_avg_sq"], sb[k]["exp_avg_sq"])
    # the split run's log has each step once, with the same losses as the single run
    rows_one = list(csv.DictReader(open(tmp_path / "one" / "log.csv")))
    rows_split = list(csv.DictReader(open(tmp_path / "split" / "log.csv")))
    assert [r["step"] for r in rows_split] == ["1", "2", "3"]
    assert [r["loss_total"] for r in rows_one] == [r["loss_total"] for r in rows_split]
    ck = latest_checkpoint(tmp_path / "split")
    assert ck is not None and ck.name == "step_00000003"
    assert (ck / "model.safetensors").is_file() and (ck / "config.json").is_file()
    exported = FastGHA.from_pretrained(tmp_path / "split" / "model")
    for (name, a), (_, b) in zip(exported.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.equal(a, b), name
    # checkpoints: the last K kept; validation grid and PSNR written
    assert sorted(p.name for p in (tmp_path / "one" / "checkpoints").iterdir()) == ["step_00000002", "step_00000003"]
    assert (tmp_path / "one" / "val" / "step_00000002.png").is_file()
    rows = list(csv.DictReader(open(tmp_path / "one" / "val.csv")))
    assert rows[0]["step"] == "2" and float(rows[0]["psnr"]) > 0
    header = next(csv.reader(open(tmp_path / "one" / "log.csv")))
    assert {f"loss_{k}" for k in LOSS_TERMS} <= set(header) and "samples_per_s" in header


def test_stream_sampler_splits_ranks_and_resumes():
    full = list(StreamSampler(10, batch_size=2, rank=0, world_size=1, seed=3, start_step=0, steps=7))
    assert sorted(full[:10]) == list(range(10))  # epoch 0 is a permutation
    r0 = list(StreamSampler(10, 2, 0, 2, 3, 0, 3))
    r1 = list(StreamSampler(10, 2, 1, 2, 3, 0, 3))
    interleaved = [x for s in range(3) for x in r0[2 * s : 2 * s + 2] + r1[2 * s : 2 * s + 2]]
    assert interleaved == full[:12]  # two ranks together consume the single-rank stream
    assert list(StreamSampler(10, 2, 0, 1, 3, 4, 7)) == full[8:]


def test_train_config_presets_and_files(tmp_path):
    paper, tiny = load_train_config("paper"), load_train_config("tiny")
    assert (paper.lr, paper.lr_deform) == (5e-5, 5e-4)
    assert (paper.loss.w_ssim, paper.loss.w_perc, paper.loss.w_sil, paper.loss.w_geo) == (1.0, 0.5, 1.0, 0.5)
    assert tiny.model == "tiny" and tiny.lr > paper.lr
    f = tmp_path / "run.json"
    f.write_text('{"preset": "tiny", "steps": 7, "loss": {"w_geo": 0.0}}')
    cfg = load_train_config(str(f))
    assert cfg.steps == 7 and cfg.loss.w_geo == 0.0 and cfg.loss.w_sil == 1.0 and cfg.lr == tiny.lr
    f.write_text('{"stepz": 7}')
    with pytest.raises(ValueError, match="stepz"):
        load_train_config(str(f))


def test_evaluate_protocol_report_and_ablations(tmp_path, toy_data):
    from fastgha_core.train.evaluate import EvalConfig, evaluate, select_protocol, write_report

    seq = toy_data.sequence()
    cfg = EvalConfig(num_inputs=4, num_target_timesteps=2, num_target_views=2, backend="cpu")
    proto = select_protocol(seq, cfg)
    assert len(set(proto.input_timesteps)) == 3  # 4 timesteps: 3 distinct input expressions, >= 1 left as novel
    assert not set(proto.target_timesteps) & set(proto.input_timesteps)  # novel expressions
    assert not set(proto.target_cameras) & set(proto.input_cameras)  # novel views
    torch.manual_seed(0)
    model = FastGHA(toy_model_config(32)).eval()
    report = evaluate(model, [seq], cfg, out_dir=tmp_path, progress=False)
    n = len(proto.target_timesteps) * 2
    assert report["num_images"] == n and set(report["summary"]) == {"psnr", "ssim", "lpips", "csim", "akd"}
    assert report["summary"]["lpips"] is None and report["summary"]["csim"] is None  # unavailable, not faked
    assert 0 < report["summary"]["psnr"] < 100 and -1 <= report["summary"]["ssim"] <= 1
    assert (tmp_path / "comparison.png").is_file()
    md = write_report(report, tmp_path / "r.json", tmp_path)
    assert "strong expressions" in md and (tmp_path / "r.json").is_file()
    # an untrained deformation MLP is the identity (zero-initialised output), so static == none
    static = evaluate(model, [seq], EvalConfig(num_inputs=4, num_target_timesteps=2, num_target_views=2, backend="cpu", ablation="static"), progress=False)
    assert static["summary"]["psnr"] == pytest.approx(report["summary"]["psnr"], abs=1e-4)


def test_cosine_schedule_warms_up_then_anneals_to_the_floor(tmp_path, toy_data):
    tr = _trainer(tmp_path, toy_data, steps=10, warmup_steps=2, lr_schedule="cosine", min_lr_ratio=0.1)
    lrs = []
    for _ in range(10):
        lrs.append(tr.optimizer.param_groups[0]["lr"])
        tr.optimizer.step()
        tr.scheduler.step()
    base = 2e-3
    assert lrs[0] == pytest.approx(base / 2) and lrs[1] == pytest.approx(base)
    # after warmup the rate falls monotonically: halfway it is the mean of start and floor
    assert all(a >= b for a, b in zip(lrs[1:], lrs[2:]))
    assert lrs[6] == pytest.approx(base * (0.1 + 0.9 * 0.5))
    assert tr.optimizer.param_groups[0]["lr"] == pytest.approx(base * 0.1)
    with pytest.raises(ValueError, match="lr_schedule"):
        _trainer(tmp_path / "bad", toy_data, lr_schedule="linear")


def test_evaluate_renders_view_blended_avatars_per_camera(toy_data):
    """With per-view data (here on the network's depth, ``view_blend_surface_only=False``) the report
    weights each target camera's render by view blending: an infinite tau (every factor 1) gives the
    unweighted figures exactly, a finite one changes them."""
    from fastgha_core.train.evaluate import EvalConfig, evaluate

    seq = toy_data.sequence()
    cfg = EvalConfig(num_inputs=4, num_target_timesteps=2, num_target_views=2, backend="cpu")
    torch.manual_seed(0)
    model = FastGHA(toy_model_config(32)).eval()
    gcfg = model.config.gaussians
    off = evaluate(model, [seq], cfg, progress=False)["summary"]["psnr"]
    gcfg.view_blend_surface_only = False
    gcfg.view_blend_tau_deg = 1e9
    flat = evaluate(model, [seq], cfg, progress=False)["summary"]["psnr"]
    gcfg.view_blend_tau_deg = 5.0
    sharp = evaluate(model, [seq], cfg, progress=False)["summary"]["psnr"]
    assert flat == pytest.approx(off, abs=1e-4)
    assert abs(sharp - off) > 1e-3


def test_input_view_depth_terms_reach_the_network(tmp_path, toy_data):
    """``w_input_depth`` and ``w_cross_view`` on: the batch's input depths become ray distances, both
    terms are logged and their gradients reach the reconstruction network (not only the deformation)."""
    from fastgha_core.train.losses import LossConfig

    loss = LossConfig(w_perc=0.0, w_input_depth=1.0, w_cross_view=1.0)
    tr = _trainer(tmp_path, toy_data, loss=loss)
    batch = collate_toy([toy_data[0]])
    assert batch.input_depths is not None and float(batch.input_depths.max()) > 0
    terms, _ = tr.compute_losses(batch)
    core = [p for n, p in tr.model.named_parameters() if p.requires_grad and not n.startswith("deform.")]
    for name in ("indepth", "xview"):
        assert torch.isfinite(terms[name]) and float(terms[name].detach()) > 0, name
        grads = torch.autograd.grad(terms[name], core, retain_graph=True, allow_unused=True)
        assert any(g is not None and g.abs().sum() > 0 for g in grads), f"{name} does not reach the network"
    off, _ = _trainer(tmp_path / "off", toy_data).compute_losses(batch)
    assert float(off["indepth"]) == float(off["xview"]) == 0.0


def test_a_fresh_run_refuses_a_folder_with_checkpoints_and_a_resume_keeps_val_csv_single(tmp_path, toy_data):
    """A fresh run into an old run's folder used to delete its own checkpoint (the pruning keeps the
    newest steps: the old run's) and append to val.csv; a resumed run re-validated past its checkpoint."""
    first = _trainer(tmp_path, toy_data, ckpt_every=2, val_every=1, val_samples=1)
    first.fit(steps=3)  # checkpoints at 2 and 3, validation rows 1, 2, 3
    with pytest.raises(ValueError, match=r"already holds a training run \(checkpoint step_00000003\): add --resume"):
        _trainer(tmp_path, toy_data, ckpt_every=2).fit(steps=2)
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step_00000002", "step_00000003"]
    import shutil

    shutil.rmtree(tmp_path / "checkpoints" / "step_00000003")  # as if killed after step 2's checkpoint
    resumed = _trainer(tmp_path, toy_data, ckpt_every=2, val_every=1, val_samples=1)
    resumed.fit(steps=4, resume=True)
    assert [r["step"] for r in csv.DictReader(open(tmp_path / "val.csv"))] == ["1", "2", "3", "4"]


def test_resuming_with_another_model_is_one_clear_error(tmp_path, toy_data):
    _trainer(tmp_path, toy_data, ckpt_every=1).fit(steps=1)
    cfg = TrainConfig(model="toy", val_every=0, ckpt_every=0, render_backend="cpu")
    mc = toy_model_config(32)
    mc.deform.hidden_size *= 2  # another deformation MLP: other tensor shapes
    other = FastGHA(mc)
    with pytest.raises(ValueError, match=r"holds another model than this run's: 0 tensors missing, 0 unexpected, [1-9]\d* of other shapes") as e:
        Trainer(cfg, other, toy_data, tmp_path, dist=DistInfo(), collate_fn=collate_toy).fit(steps=2, resume=True)
    assert len(str(e.value)) < 400  # torch's message listed every tensor (22,856 characters for tiny -> paper)


@pytest.mark.parametrize("config, message", [
    ({"preset": "tiny", "steps": "2"}, r"train config.steps must be an integer, got '2'"),
    ({"preset": "tiny", "lr": "fast"}, r"train config.lr must be a number"),
    ({"preset": "tiny", "betas": 0.9}, r"train config.betas must be a list of numbers"),
    ({"preset": "tiny", "loss": 5}, r"loss must be an object of fields, got 5"),
    ({"preset": "tiny", "loss": {"w_geo": "x"}}, r"loss.w_geo must be a number, got 'x'"),
    ({"preset": "tiny", "input_camera_noise": {"enabled": "yes"}}, r"input_camera_noise.enabled must be true or false"),
])
def test_config_json_values_of_the_wrong_type_are_refused_when_read(tmp_path, config, message):
    """They passed and failed minutes later in training with a TypeError (exit 1, a traceback)."""
    import json

    path = tmp_path / "c.json"
    path.write_text(json.dumps(config))
    with pytest.raises(ValueError, match=message):
        load_train_config(str(path))


def test_evaluation_says_when_the_sequence_has_fewer_targets_than_asked(toy_data, caplog):
    """``--views 8 --expressions 4`` on a small sequence quietly scored fewer images than asked."""
    from fastgha_core.train.evaluate import EvalConfig, select_protocol

    seq = toy_data.sequence()
    with caplog.at_level("WARNING", logger="fastgha_core.train.evaluate"):
        proto = select_protocol(seq, EvalConfig(num_inputs=4, num_target_timesteps=50, num_target_views=50, backend="cpu"))
    assert len(proto.target_timesteps) < 50 and len(proto.target_cameras) < 50
    assert f"{len(proto.target_timesteps)} of 50 target expressions and {len(proto.target_cameras)} of 50 target views" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="fastgha_core.train.evaluate"):
        select_protocol(seq, EvalConfig(num_inputs=4, num_target_timesteps=1, num_target_views=1, backend="cpu"))
    assert "target expressions" not in caplog.text
