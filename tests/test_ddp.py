"""DistributedDataParallel on 2 CPU processes (gloo): after a few steps on different data the
parameters are identical on both ranks, and equal to a single-process run on the union of the data
(the gradients are averaged)."""

from __future__ import annotations

import os
import socket

import torch
import torch.multiprocessing as mp


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE=str(world), RANK=str(rank), LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    from fastgha_core.model.fastgha import FastGHA
    from fastgha_core.train.toy import ToyDataset, collate_toy, toy_model_config
    from fastgha_core.train.trainer import TrainConfig, Trainer, init_distributed

    dist = init_distributed("cpu")
    try:
        data = ToyDataset(length=8, size=32, seed=0)
        torch.manual_seed(1000 + rank)  # different initial weights per rank: DDP must broadcast rank 0's
        model = FastGHA(toy_model_config(32))
        cfg = TrainConfig(model="toy", lr=2e-3, lr_deform=2e-3, val_every=0, ckpt_every=0, log_every=1, render_backend="cpu")
        trainer = Trainer(cfg, model, data, out_dir, dist=dist, collate_fn=collate_toy)
        trainer.fit(steps=2)
        torch.save({k: v.clone() for k, v in model.state_dict().items()}, os.path.join(out_dir, f"rank{rank}.pt"))
    finally:
        torch.distributed.destroy_process_group()


def test_ddp_two_cpu_ranks_end_with_identical_parameters(tmp_path):
    mp.spawn(_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    a = torch.load(tmp_path / "rank0.pt")
    b = torch.load(tmp_path / "rank1.pt")
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # training changed the weights (the test would pass trivially otherwise)
    from fastgha_core.model.fastgha import FastGHA

    exported = FastGHA.from_pretrained(tmp_path / "model")
    torch.manual_seed(1000)
    from fastgha_core.train.toy import toy_model_config

    init = FastGHA(toy_model_config(32)).state_dict()
    changed = [k for k in a if a[k].is_floating_point() and not torch.equal(a[k], init[k])]
    assert changed, "no parameter changed during DDP training"
    for k, v in exported.state_dict().items():
        assert torch.equal(v, a[k]), k
    rows = (tmp_path / "log.csv").read_text().splitlines()
    assert len(rows) == 3  # header + 2 steps, written by rank 0 only
