"""``fastgha bench mlp``: the deformation MLP per configuration, as achieved GFLOP/s next to matmul.

Configurations, one N-Gaussian avatar, one expression per call, under ``torch.inference_mode``:

- ``fp32_plain``: ``DeformationMLP.forward`` (first layer over [feature, PE(xyz), expression]);
- ``fp32_split``: ``forward_split`` on the cached first-layer term (what ``animate`` runs);
- ``bf16_split``: the same under CPU bf16 autocast;
- ``fp32_split_compiled`` / ``bf16_split_compiled``: ``torch.compile`` of the per-chunk tail;
- ``fp32_split_batchB``: B avatars in one call (concatenated rows, one expression each) — the
  "batch the MLP across sessions" idea; reported per avatar.

FLOPs counted are those of the path run (2 per multiply-add; the plain path includes its first
layer, the split path only ``W_z z`` and the layers after it). The machine's matmul throughput is
measured in the same run: a 2048³ ``torch.mm`` in fp32 and bf16, and the MLP's own shape
(``[chunk, H] x [H, H]``) for reference.
"""

from __future__ import annotations

import logging
import time

import torch

from ._common import bench_model, load_average, positive_int, time_fn

log = logging.getLogger(__name__)


def add_arguments(parser) -> None:
    parser.add_argument("--mlp-model", default="tiny", help="model preset or folder whose deformation MLP is measured (default tiny)")
    parser.add_argument("--mlp-gaussians", type=positive_int, default=None, help="Gaussians per avatar (default 65536, --quick 16384)")
    parser.add_argument("--mlp-batch", type=positive_int, default=4, help="avatars per call in the batched configuration (default 4)")
    parser.add_argument("--mlp-compile", choices=("auto", "on", "off"), default="auto", help="measure torch.compile (auto: not with --quick)")


def matmul_gflops(dtype: torch.dtype, m: int, k: int, n: int, repeats: int) -> float:
    a = torch.randn(m, k).to(dtype)
    b = torch.randn(k, n).to(dtype)
    with torch.inference_mode():
        t = time_fn(lambda: torch.mm(a, b), repeats)
    return 2.0 * m * k * n / (t.wall_ms * 1e-3) / 1e9


def mlp_flops(deform, n: int, split: bool) -> float:
    """Multiply-add FLOPs (x2) of one call on ``n`` Gaussians and one expression."""
    h, layers = deform.cfg.hidden_size, deform.cfg.num_layers
    inp = deform.feature_dim + deform.pe_dim + deform.expr_dim
    tail = (layers - 1) * h * h + 6 * h
    if split:
        return 2.0 * (n * tail + deform.expr_dim * h) + n * h  # + adding W_z z to every row
    return 2.0 * n * (inp * h + tail)


def run(args) -> dict:
    quick = bool(getattr(args, "quick", False))
    name = getattr(args, "mlp_model", "tiny") or "tiny"
    n = getattr(args, "mlp_gaussians", None) or (16_384 if quick else 65_536)
    batch = max(1, int(getattr(args, "mlp_batch", 4) or 4))
    compile_opt = getattr(args, "mlp_compile", "auto") or "auto"
    do_compile = compile_opt == "on" or (compile_opt == "auto" and not quick)
    repeats = 3 if quick else 15
    model = bench_model(name)
    deform = model.deform.eval()
    cfg = deform.cfg
    gen = torch.Generator().manual_seed(0)
    feats = torch.randn(n, deform.feature_dim, generator=gen)
    xyz = 0.1 * torch.randn(n, 3, generator=gen)
    expr = 0.3 * torch.rand(deform.expr_dim, generator=gen)
    with torch.inference_mode():
        partial = deform.precompute(feats, xyz)  # [N, H]
    load0 = load_average()

    mm_repeats = 3 if quick else 7
    size = 1024 if quick else 2048
    peak = {
        "fp32": matmul_gflops(torch.float32, size, size, size, mm_repeats),
        "bf16": matmul_gflops(torch.bfloat16, size, size, size, mm_repeats),
    }
    shape = {
        "fp32": matmul_gflops(torch.float32, 8192, cfg.hidden_size, cfg.hidden_size, repeats),
        "bf16": matmul_gflops(torch.bfloat16, 8192, cfg.hidden_size, cfg.hidden_size, repeats),
    }
    print(f"MLP benchmark: model {model.config.name!r} deformation MLP {cfg.hidden_size} x {cfg.num_layers}, {n} Gaussians, "
          f"torch threads {torch.get_num_threads()}")
    print(f"matmul {size}³: fp32 {peak['fp32']:.0f} GFLOP/s, bf16 {peak['bf16']:.0f} GFLOP/s; "
          f"MLP-shaped [8192,{cfg.hidden_size}]x[{cfg.hidden_size},{cfg.hidden_size}]: fp32 {shape['fp32']:.0f}, bf16 {shape['bf16']:.0f}")

    def bf16_ctx():
        return torch.autocast("cpu", dtype=torch.bfloat16)

    configs: dict[str, tuple] = {}

    def plain():
        with torch.inference_mode():
            deform(feats, xyz, expr)

    def split():
        with torch.inference_mode():
            deform.forward_split(partial, expr)

    def split_bf16():
        with torch.inference_mode(), bf16_ctx():
            deform.forward_split(partial, expr)

    configs["fp32_plain"] = (plain, "fp32", mlp_flops(deform, n, False), 1)
    configs["fp32_split"] = (split, "fp32", mlp_flops(deform, n, True), 1)
    configs["bf16_split"] = (split_bf16, "bf16", mlp_flops(deform, n, True), 1)

    if batch > 1:
        big = partial.repeat(batch, 1)  # [B*N, H]: B avatars' cached terms side by side
        exprs = expr.expand(batch, -1).contiguous()

        def batched():
            with torch.inference_mode():
                w_z = deform.first.weight[:, deform.feature_dim + deform.pe_dim:]
                ez = torch.nn.functional.linear(exprs, w_z).repeat_interleave(n, dim=0)  # [B*N, H]
                out = [deform._tail_raw(big[s:s + 8192] + ez[s:s + 8192]) for s in range(0, batch * n, 8192)]
                torch.cat(out)

        configs[f"fp32_split_batch{batch}"] = (batched, "fp32", batch * mlp_flops(deform, n, True), batch)

    compile_info = {"measured": do_compile}
    if do_compile:
        try:
            t0 = time.perf_counter()
            tail_c = torch.compile(deform._tail_raw, dynamic=False)
            w_z = deform.first.weight[:, deform.feature_dim + deform.pe_dim:]

            def compiled(ctx=None):
                with torch.inference_mode():
                    ez = torch.nn.functional.linear(expr, w_z)
                    torch.cat([tail_c(partial[s:s + 8192] + ez) for s in range(0, n, 8192)])

            def compiled_bf16():
                with torch.inference_mode(), bf16_ctx():
                    ez = torch.nn.functional.linear(expr, w_z)
                    torch.cat([tail_c(partial[s:s + 8192] + ez) for s in range(0, n, 8192)])

            compiled()
            compiled_bf16()
            compile_info["compile_s"] = time.perf_counter() - t0
            configs["fp32_split_compiled"] = (compiled, "fp32", mlp_flops(deform, n, True), 1)
            configs["bf16_split_compiled"] = (compiled_bf16, "bf16", mlp_flops(deform, n, True), 1)
        except Exception as e:  # inductor needs a C++ compiler; report instead of failing the run
            compile_info["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:200]}"
            log.warning("torch.compile failed: %s", compile_info["error"])

    rows = []
    print(f"{'config':>24} {'ms/avatar':>10} {'GFLOP/s':>8} {'of matmul':>9}")
    for cname, (fn, prec, flops, per) in configs.items():
        t = time_fn(fn, repeats)
        gf = flops / (t.wall_ms * 1e-3) / 1e9
        row = {"config": cname, "precision": prec, "ms": t.wall_ms, "ms_per_avatar": t.wall_ms / per, "cpu_ms": t.cpu_ms,
               "gflop": flops / 1e9, "gflops": gf, "fraction_of_matmul": gf / peak[prec], "fraction_of_shaped_matmul": gf / shape[prec]}
        rows.append(row)
        print(f"{cname:>24} {row['ms_per_avatar']:>10.2f} {gf:>8.1f} {row['fraction_of_matmul']:>9.2f}", flush=True)
    best = max(rows, key=lambda r: r["fraction_of_matmul"])
    served = next(r for r in rows if r["config"] == "fp32_split")
    return {
        "model": model.config.name,
        "hidden_size": cfg.hidden_size,
        "num_layers": cfg.num_layers,
        "gaussians": n,
        "matmul_gflops": peak,
        "matmul_gflops_mlp_shape": shape,
        "matmul_size": size,
        "rows": rows,
        "compile": compile_info,
        "best_config": best["config"],
        "load_average_start": load0,
        "load_average_end": load_average(),
        "summary": {"mlp_fraction_of_matmul": best["fraction_of_matmul"], "mlp_fraction_of_matmul_fp32_split": served["fraction_of_matmul"]},
    }
