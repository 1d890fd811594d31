"""The reconstruction network at toy sizes: config, shapes, gradients, saving, pretrained encoders,
Gaussian head geometry, prepare/reconstruct/animate, avatar files."""

from __future__ import annotations

import json
import math

import pytest
import torch
from torch.testing import assert_close

from fastgha_core.cameras import Cameras, orbit_cameras
from fastgha_core.config import (
    PRESETS,
    DecoderConfig,
    DeformConfig,
    DinoConfig,
    FastGHAConfig,
    GaussianHeadConfig,
    TransformerConfig,
    VAEConfig,
    get_preset,
)
from fastgha_core.constants import BACKGROUND_RGB
from fastgha_core.model.avatar import CanonicalAvatar
from fastgha_core.model.decoder import cross_view_attention
from fastgha_core.model.fastgha import FastGHA, load_model
from fastgha_core.model.gaussian_head import GaussianHead, matrix_to_quaternion, quaternion_multiply

S = 32  # toy input size


def toy_config(frozen: bool = False, **changes) -> FastGHAConfig:
    cfg = FastGHAConfig(
        name="toy",
        expression_space="ict53",
        expression_dim=53,
        input_size=S,
        render_size=S,
        max_views=8,
        dino=DinoConfig(
            hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, patch_size=16,
            num_register_tokens=2, feature_layers=(1, 2), out_channels=16, frozen=frozen,
        ),
        vae=VAEConfig(block_out_channels=(8, 8, 8, 8), layers_per_block=1, norm_num_groups=4, frozen=frozen),
        transformer=TransformerConfig(hidden_size=32, num_layers=2, num_heads=2),
        decoder=DecoderConfig(block_out_channels=(8, 8, 8, 8), layers_per_block=1, norm_num_groups=4),
        gaussians=GaussianHeadConfig(feature_dim=8, prune_opacity=0.0),
        deform=DeformConfig(hidden_size=16, num_layers=2, pe_freqs=2),
    )
    return cfg.copy(**changes) if changes else cfg


def toy_inputs(v: int, b: int | None = None, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    cams = orbit_cameras(max(v, 2), width=S, height=S)[:v]
    imgs = torch.rand(v, 3, S, S, generator=g)
    if b is None:
        return imgs, cams
    return imgs.expand(b, -1, -1, -1, -1).clone(), cams.K.expand(b, -1, -1, -1), cams.w2c.expand(b, -1, -1, -1)


@pytest.fixture(scope="module")
def toy_model() -> FastGHA:
    torch.manual_seed(0)
    return FastGHA(toy_config()).eval()


# ---------------------------------------------------------------- config
def test_presets_record_space_size_and_freezing():
    paper, tiny = get_preset("paper"), get_preset("tiny")
    assert (paper.expression_space, paper.expression_dim, paper.input_size, paper.encoders_frozen) == ("flame120", 120, 512, True)
    assert (tiny.expression_space, tiny.expression_dim, tiny.input_size, tiny.encoders_frozen) == ("ict53", 53, 128, False)
    assert paper.gaussians.channels == 44 and tiny.gaussians.channels == 44
    assert paper.token_channels == 266
    assert get_preset("tiny") is not PRESETS["tiny"]
    with pytest.raises(ValueError, match="unknown model preset"):
        get_preset("huge")


def test_config_json_round_trip_and_unknown_fields():
    for name in PRESETS:
        cfg = get_preset(name)
        back = FastGHAConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
        assert back == cfg
    d = get_preset("tiny").to_dict()
    d["transformer"]["width"] = 3
    with pytest.raises(ValueError, match=r"config.transformer: unknown field"):
        FastGHAConfig.from_dict(d)
    with pytest.raises(ValueError, match="divisible"):
        toy_config(input_size=36)


# ---------------------------------------------------------------- shapes
@pytest.mark.parametrize("v", [1, 2, 3, 4, 5, 6])
def test_forward_gaussians_shapes(toy_model, v):
    imgs, cams = toy_inputs(v)
    with torch.no_grad():
        (g,) = toy_model.forward_gaussians(imgs[None], cams[None])
    assert len(g) == v * S * S
    assert g.features.shape == (v * S * S, 8)
    g.validate_values()


def test_training_forward_batch(toy_model):
    imgs, K, w2c = toy_inputs(2, b=2)
    expr = torch.zeros(2, 53)
    with torch.no_grad():
        out = toy_model(imgs, K, w2c, expr)
    assert len(out.gaussians) == len(out.canonical) == 2
    # both samples hold identical inputs
    assert_close(out.canonical[0].means, out.canonical[1].means)
    # each input pixel's depth along its ray (LossConfig.w_depth_smooth): its Gaussian's distance from the camera
    assert out.view_depth.shape == (2, 2, S, S)
    centres = torch.linalg.inv(w2c[0])[:, :3, 3]
    ref = (out.canonical[0].means[: 2 * S * S].view(2, S, S, 3) - centres[:, None, None]).norm(dim=-1)
    assert_close(out.view_depth[0], ref)
    with pytest.raises(ValueError, match="expression must have shape"):
        toy_model(imgs, K, w2c, torch.zeros(2, 52))


def test_views_interact(toy_model):
    """The transformer/decoder mix views: changing view 2 changes the Gaussians of view 1."""
    imgs, cams = toy_inputs(2)
    imgs2 = imgs.clone()
    imgs2[1] = torch.rand(3, S, S)
    with torch.no_grad():
        (a,) = toy_model.forward_gaussians(imgs[None], cams[None])
        (b,) = toy_model.forward_gaussians(imgs2[None], cams[None])
    n = S * S
    assert (a.means[:n] - b.means[:n]).abs().max() > 1e-6


# ---------------------------------------------------------------- gradients
def _loss(out) -> torch.Tensor:
    g = out.gaussians[0]
    w = torch.Generator().manual_seed(1)
    total = 0.0
    for t in (g.means, g.quats, g.scales, g.opacities, g.colors):
        total = total + (t * torch.randn(t.shape, generator=w)).sum()
    return total


@pytest.mark.parametrize("frozen", [True, False])
def test_gradients_reach_trainable_and_not_frozen(frozen):
    torch.manual_seed(0)
    model = FastGHA(toy_config(frozen=frozen)).train()
    torch.nn.init.normal_(model.deform.out.weight, std=0.1)  # zero-init output would block grads into the MLP
    imgs, K, w2c = toy_inputs(2, b=1)
    _loss(model(imgs, K, w2c, torch.randn(1, 53))).backward()
    no_grad = []
    for name, p in model.named_parameters():
        if name.endswith("embeddings.mask_token"):  # only used for masked-image pretraining
            continue
        if p.requires_grad and (p.grad is None or p.grad.abs().sum() == 0):
            no_grad.append(name)
        if not p.requires_grad:
            assert p.grad is None, name
    assert not no_grad, no_grad
    frozen_names = [n for n, p in model.named_parameters() if not p.requires_grad]
    if frozen:
        assert any(n.startswith("semantic.vit.") for n in frozen_names)
        assert any(n.startswith("colour.") for n in frozen_names)
        assert not any(n.startswith(("semantic.proj", "semantic.fuse", "transformer.", "decoder.", "deform.")) for n in frozen_names)
        assert not model.semantic.vit.training and not model.colour.training and model.transformer.training
    else:
        assert frozen_names == []


# ---------------------------------------------------------------- decoder attention
def test_cross_view_attention_matches_diffusers_for_one_view_and_mixes_views(toy_model):
    attn = toy_model.decoder.decoder.mid_block.attentions[0]
    x = torch.randn(3, 8, 4, 4)
    with torch.no_grad():
        assert_close(cross_view_attention(attn, x, 1), attn(x))
        joint = cross_view_attention(attn, x[:2], 2)
        x2 = x[:2].clone()
        x2[1] = torch.randn(8, 4, 4)  # (a constant shift would vanish in the per-view GroupNorm)
        joint2 = cross_view_attention(attn, x2, 2)
    assert (joint[0] - joint2[0]).abs().max() > 1e-6  # view 0 sees view 1


# ---------------------------------------------------------------- save / load
def test_save_pretrained_round_trip_is_bit_exact(toy_model, tmp_path):
    toy_model.save_pretrained(tmp_path / "m")
    assert {p.name for p in (tmp_path / "m").iterdir()} == {"config.json", "model.safetensors"}
    loaded = FastGHA.from_pretrained(tmp_path / "m")
    assert loaded.config == toy_model.config
    imgs, K, w2c = toy_inputs(3, b=1)
    expr = torch.randn(1, 53)
    with torch.no_grad():
        a, b = toy_model(imgs, K, w2c, expr), loaded(imgs, K, w2c, expr)
    for f in ("means", "quats", "scales", "opacities", "colors", "features"):
        assert torch.equal(getattr(a.gaussians[0], f), getattr(b.gaussians[0], f)), f
    via_loader = load_model(str(tmp_path / "m"))
    assert not via_loader.training and via_loader.config.name == "toy"
    with pytest.raises(ValueError, match="must contain config.json"):
        FastGHA.from_pretrained(tmp_path)


def test_load_model_preset_name_and_unknown_names():
    import fastgha_core

    model = fastgha_core.load_model("tiny")  # shipped weights when present, else random init
    assert model.config.name == "tiny" and model.config.expression_space == "ict53" and not model.training
    assert model.expression_space.dim == model.config.expression_dim
    with pytest.raises(ValueError, match="unknown model"):
        load_model("no-such-model-or-folder")


# ---------------------------------------------------------------- paper preset
def _transformer_params(c_in: int, d: int, layers: int, ratio: float = 4.0) -> int:
    h = int(d * ratio)
    block = 2 * 2 * d + (d * 3 * d + 3 * d) + (d * d + d) + (d * h + h) + (h * d + d)
    return c_in * d + d + layers * block + 2 * d


def _deform_params(f: int, pe: int, e: int, h: int, layers: int) -> int:
    return (f + pe + e) * h + h + (layers - 1) * (h * h + h) + h * 6 + 6


def test_paper_preset_builds_on_meta_device():
    cfg = get_preset("paper")
    with torch.device("meta"):
        model = FastGHA(cfg)
    counts = model.parameter_counts()
    print("\npaper preset parameters per module:")
    for k, v in counts.items():
        print(f"  {k:12s} {v:>13,d}")
    assert all(p.device.type == "meta" for p in model.parameters())
    assert counts["transformer"] == _transformer_params(266, 512, 8)
    assert counts["deform"] == _deform_params(32, 3 + 6 * 6, 120, 256, 6)
    assert 300e6 < counts["dino_vit"] < 306e6  # dinov3-vitl16 is a 0.3B model
    assert 30e6 < counts["vae_encoder"] < 40e6  # the SD VAE encoder is ~34M
    dec = model.decoder.decoder
    assert (dec.conv_in.in_channels, dec.conv_out.out_channels) == (512, 44)
    assert counts["trainable"] == counts["total"] - counts["dino_vit"] - counts["vae_encoder"]


def test_tiny_preset_parameter_counts():
    model = FastGHA(get_preset("tiny"))
    counts = model.parameter_counts()
    print("\ntiny preset parameters per module:")
    for k, v in counts.items():
        print(f"  {k:12s} {v:>13,d}")
    assert counts["transformer"] == _transformer_params(64 + 4 + 6, 192, 4)
    assert counts["deform"] == _deform_params(32, 3 + 6 * 4, 53, 48, 4)
    assert counts["trainable"] == counts["total"]  # tiny trains its encoders from scratch


# ---------------------------------------------------------------- pretrained encoder folders
def _write_pretrained(tmp_path, cfg: FastGHAConfig):
    from diffusers import AutoencoderKL
    from transformers import DINOv3ViTModel

    torch.manual_seed(5)
    dino = DINOv3ViTModel(cfg.dino.to_hf())
    dino.save_pretrained(tmp_path / "dino")
    n = len(cfg.vae.block_out_channels)
    vae = AutoencoderKL(
        down_block_types=("DownEncoderBlock2D",) * n,
        up_block_types=("UpDecoderBlock2D",) * n,
        block_out_channels=cfg.vae.block_out_channels,
        layers_per_block=cfg.vae.layers_per_block,
        norm_num_groups=cfg.vae.norm_num_groups,
        latent_channels=4,
        scaling_factor=0.5,
    )
    vae.save_pretrained(tmp_path / "vae")
    return dino, vae


def test_pretrained_encoder_folders_load_frozen(tmp_path):
    cfg = toy_config(frozen=False)
    dino, vae = _write_pretrained(tmp_path, cfg)
    FastGHA(cfg).save_pretrained(tmp_path / "model")
    model = load_model(str(tmp_path / "model"), dino_weights=tmp_path / "dino", vae_weights=str(tmp_path / "vae"))
    for k, v in dino.state_dict().items():
        assert torch.equal(model.semantic.vit.state_dict()[k], v), k
    for k, v in vae.encoder.state_dict().items():
        assert torch.equal(model.colour.encoder.state_dict()[k], v), k
    assert torch.equal(model.colour.quant_conv.weight, vae.quant_conv.weight)
    dec_own, dec_pre = model.decoder.decoder.state_dict(), vae.decoder.state_dict()
    assert torch.equal(dec_own["mid_block.attentions.0.to_q.weight"], dec_pre["mid_block.attentions.0.to_q.weight"])
    assert torch.equal(dec_own["conv_in.weight"][:, :4], dec_pre["conv_in.weight"])
    assert torch.equal(dec_own["conv_out.weight"][1:4], dec_pre["conv_out.weight"])  # rgb channels
    assert model.config.encoders_frozen and model.colour.cfg.scaling_factor == 0.5
    model.train()
    assert not model.semantic.vit.training and not model.colour.training
    assert not any(p.requires_grad for p in model.semantic.vit.parameters())
    assert not any(p.requires_grad for p in model.colour.parameters())
    assert all(p.requires_grad for p in model.transformer.parameters())
    # The frozen state travels with save_pretrained.
    model.save_pretrained(tmp_path / "model2")
    again = FastGHA.from_pretrained(tmp_path / "model2")
    assert again.config.encoders_frozen and not any(p.requires_grad for p in again.colour.parameters())


def test_pretrained_folder_errors(tmp_path):
    cfg = toy_config()
    with pytest.raises(ValueError, match="no config.json"):
        FastGHA(cfg, dino_weights=tmp_path / "missing")
    from transformers import DINOv3ViTModel

    other = cfg.dino.to_hf()
    other.hidden_size = 48
    DINOv3ViTModel(other).save_pretrained(tmp_path / "dino48")
    with pytest.raises(ValueError, match="hidden_size=48 \\(model expects 32\\)"):
        FastGHA(cfg, dino_weights=tmp_path / "dino48")


# ---------------------------------------------------------------- Gaussian head
def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)


def test_quaternion_helpers():
    q = torch.nn.functional.normalize(torch.randn(200, 4, dtype=torch.float64), dim=-1)
    R = _quat_to_matrix(q)
    q2 = matrix_to_quaternion(R)
    assert_close(_quat_to_matrix(q2), R)
    p = torch.nn.functional.normalize(torch.randn(200, 4, dtype=torch.float64), dim=-1)
    assert_close(_quat_to_matrix(quaternion_multiply(p, q)), _quat_to_matrix(p) @ R)


def test_gaussian_head_zero_maps_geometry():
    cfg = GaussianHeadConfig(feature_dim=4, depth_range=0.3, min_scale_px=0.5, max_scale_px=8.0)
    head = GaussianHead(cfg)
    cams = orbit_cameras(3, radius=1.2, width=16, height=12)
    maps = torch.zeros(1, 3, 16, 12, 16)
    (g,) = head(maps, cams[None])
    # every centre projects back to its own pixel centre, at distance |c| from the camera
    uv, _ = cams.project(g.means.view(3, -1, 3))
    v, u = torch.meshgrid(torch.arange(12) + 0.5, torch.arange(16) + 0.5, indexing="ij")
    assert_close(uv, torch.stack([u, v], -1).reshape(1, -1, 2).expand(3, -1, -1), atol=1e-3, rtol=0)
    dist = (g.means.view(3, -1, 3) - cams.centers[:, None]).norm(dim=-1)
    assert_close(dist, torch.full_like(dist, 1.2), atol=1e-5, rtol=0)
    # scale = footprint * sqrt(min * max) at sigmoid(0); footprint = depth / focal
    f = cams.K[0, 0, 0]
    assert_close(g.scales, torch.full_like(g.scales, float(1.2 / f * math.sqrt(0.5 * 8.0))), rtol=1e-4, atol=0)
    # zero quaternion channels = identity in the camera frame = the camera-to-world rotation
    assert_close(_quat_to_matrix(g.quats.view(3, -1, 4)[:, 0]), cams.c2w[:, :3, :3], atol=1e-5, rtol=0)
    assert_close(g.opacities, torch.full_like(g.opacities, 0.5))


def test_gaussian_head_rgb_residual_starts_at_the_input_pixel_colour():
    cams = orbit_cameras(2, width=8, height=6)
    maps = torch.zeros(1, 2, 16, 6, 8)
    images = torch.rand(1, 2, 3, 6, 8)
    (g,) = GaussianHead(GaussianHeadConfig(feature_dim=4, rgb_residual=True))(maps, cams[None], images)
    expect = images[0].clamp(0.01, 0.99).permute(0, 2, 3, 1).reshape(-1, 3)  # pixel order of the Gaussians
    assert_close(g.colors, expect, atol=1e-6, rtol=0)
    maps[:, :, 1:4] = 2.0  # a positive residual brightens every colour
    (g2,) = GaussianHead(GaussianHeadConfig(feature_dim=4, rgb_residual=True))(maps, cams[None], images)
    assert bool((g2.colors > g.colors).all())
    (g3,) = GaussianHead(GaussianHeadConfig(feature_dim=4, rgb_residual=False))(maps * 0, cams[None])
    assert_close(g3.colors, torch.full_like(g3.colors, 0.5))
    with pytest.raises(ValueError, match="rgb_residual needs the input images"):
        GaussianHead(GaussianHeadConfig(feature_dim=4, rgb_residual=True))(maps, cams[None])


def test_gaussian_head_foreground_opacity_zeroes_background_pixels():
    from fastgha_core.model.gaussian_head import foreground_weight

    cams = orbit_cameras(1, width=4, height=2)
    images = torch.ones(1, 1, 3, 2, 4)  # the white matting background ...
    images[..., 0, 1] = torch.tensor([0.5, 0.3, 0.2])  # ... one skin pixel at (row 0, col 1)
    images[..., 1, 2] = torch.tensor([0.99, 0.99, 0.99])  # ... one anti-aliased edge pixel, 1/3 foreground
    maps = torch.zeros(1, 1, 16, 2, 4)
    (g,) = GaussianHead(GaussianHeadConfig(feature_dim=4, foreground_opacity=True))(maps, cams[None], images)
    expect = torch.zeros(2, 4)
    expect[0, 1], expect[1, 2] = 0.5, 0.5 * (0.01 / 0.03)
    assert_close(g.opacities, expect.reshape(-1), atol=1e-6, rtol=0)
    assert_close(foreground_weight(images[0, 0]), expect * 2, atol=1e-6, rtol=0)


# ---------------------------------------------------------------- prepare / reconstruct / animate
def test_prepare_crops_resizes_and_mattes(toy_model):
    cam = Cameras.look_at([0.2, 0.1, 1.0], fov_deg=25, width=48, height=40)
    img = torch.rand(3, 40, 48)
    mask = torch.zeros(40, 48)
    mask[10:30, 14:34] = 1.0
    imgs, cams = toy_model.prepare([img], [cam], masks=[mask])
    assert imgs.shape == (1, 3, S, S) and (cams.width, cams.height) == (S, S)
    # a world point lands at the same relative place: crop 4 px from the left, then scale S/40
    pt = torch.tensor([[0.03, -0.02, 0.05]])
    uv0, _ = cam.project(pt)
    uv1, _ = cams[0].project(pt)
    assert_close(uv1, (uv0 - torch.tensor([4.0, 0.0])) * (S / 40), atol=1e-4, rtol=0)
    bg = torch.tensor(BACKGROUND_RGB).view(3, 1, 1)
    assert_close(imgs[0, :, :2, :2], bg.expand(3, 2, 2))  # masked-out corner is background
    with pytest.raises(ValueError, match="describes a 48x40 image"):
        toy_model.prepare([img[:, :, :40]], [cam])


def test_reconstruct_rejects_wrong_inputs(toy_model):
    imgs, cams = toy_inputs(2)
    with pytest.raises(ValueError, match=r"\[V, 3, 32, 32\].*prepare"):
        toy_model.reconstruct(torch.rand(2, 3, 64, 64), cams.resize(64, 64))
    with pytest.raises(ValueError, match="size 32x32"):
        toy_model.reconstruct(imgs, cams.resize(64, 64))
    with pytest.raises(ValueError, match="batch shape \\[2\\]"):
        toy_model.reconstruct(imgs, orbit_cameras(3, width=S, height=S))
    with pytest.raises(ValueError, match="1 to 8 views"):
        toy_model.reconstruct(torch.rand(9, 3, S, S), orbit_cameras(9, width=S, height=S))
    with pytest.raises(ValueError, match="float"):
        toy_model.reconstruct((imgs * 255).to(torch.uint8), cams)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        toy_model.reconstruct(imgs * 255, cams)


def test_reconstruct_prunes_and_animate_shapes(toy_model):
    imgs, cams = toy_inputs(2)
    avatar = toy_model.reconstruct(imgs, cams)
    assert len(avatar) == 2 * S * S  # toy prune threshold is 0
    pruned = FastGHA(toy_config(gaussians=GaussianHeadConfig(feature_dim=8, prune_opacity=0.5)))
    pruned.load_state_dict(toy_model.state_dict())
    pa = pruned.eval().reconstruct(imgs, cams)
    assert len(pa) == int((avatar.gaussians.opacities >= 0.5).sum())
    assert avatar.model_name == "toy" and avatar.expression_space == "ict53"

    one = toy_model.animate(avatar, torch.zeros(53))
    assert len(one) == len(avatar) and one.features is not None
    # zero-initialised output layer: the identity deformation
    assert torch.equal(one.means, avatar.gaussians.means) and torch.equal(one.colors, avatar.gaussians.colors)
    batch = toy_model.animate(avatar, torch.rand(3, 53))
    assert isinstance(batch, list) and len(batch) == 3 and all(len(g) == len(avatar) for g in batch)
    with pytest.raises(ValueError, match=r"\[53\] or \[B, 53\]"):
        toy_model.animate(avatar, torch.zeros(120))
    other = CanonicalAvatar(avatar.gaussians, "paper", "flame120")
    with pytest.raises(ValueError, match="expression space 'flame120'"):
        toy_model.animate(other, torch.zeros(53))


def test_animate_matches_training_forward():
    """animate (split first layer, cached on the avatar) == the training forward's deformation."""
    torch.manual_seed(0)
    model = FastGHA(toy_config()).eval()
    torch.nn.init.normal_(model.deform.out.weight, std=0.1)
    imgs, cams = toy_inputs(2)
    expr = torch.randn(53)
    avatar = model.reconstruct(imgs, cams)
    with torch.no_grad():
        out = model(imgs[None], cams.K[None], cams.w2c[None], expr[None])
    g = model.animate(avatar, expr)
    assert_close(g.means, out.gaussians[0].means)
    assert_close(g.colors, out.gaussians[0].colors)
    bf = model.animate(avatar, expr, bf16=True)
    assert_close(bf.means, g.means, atol=2e-3, rtol=0)


def test_training_forward_with_the_prior_reaches_the_reconstruction_network():
    """With the expression prior, the rendered Gaussians keep the decoder's graph (build_prior used to
    run under no_grad, so only the deformation MLP trained) and equal the no-grad forward's."""
    torch.manual_seed(0)
    cfg = toy_config()
    cfg = cfg.copy(deform=DeformConfig(hidden_size=16, num_layers=2, pe_freqs=2, prior=True))
    model = FastGHA(cfg).train()
    imgs, K, w2c = toy_inputs(2, b=1)
    expr = torch.zeros(1, 53)
    inp = torch.zeros(1, 2, 53)
    inp[0, 1, 0] = 0.5  # one photo with an expression: its displacement is undone
    out = model(imgs, K, w2c, expr, input_expressions=inp)
    g = out.gaussians[0]
    n_rec = 2 * S * S
    assert len(g) > n_rec  # the shell / mouth interior appended
    loss = g.means.sum() + g.colors.sum() + g.opacities.sum() + g.scales.sum()
    (grad,) = torch.autograd.grad(loss, [model.decoder.decoder.conv_out.weight])
    assert grad.abs().sum() > 0
    with torch.no_grad():
        ref = model(imgs, K, w2c, expr, input_expressions=inp).gaussians[0]
    assert_close(g.means.detach(), ref.means)
    assert_close(g.opacities.detach(), ref.opacities)


def test_avatar_save_load_round_trip(toy_model, tmp_path):
    imgs, cams = toy_inputs(1)
    avatar = toy_model.reconstruct(imgs, cams)
    avatar.save(tmp_path / "a.safetensors")
    back = CanonicalAvatar.load(tmp_path / "a.safetensors")
    assert (back.model_name, back.expression_space) == ("toy", "ict53")
    assert back.deform_cache is None
    for f in ("means", "quats", "scales", "opacities", "colors", "features"):
        assert torch.equal(getattr(back.gaussians, f), getattr(avatar.gaussians, f)), f
    assert back.nbytes == avatar.nbytes > 0
    expr = torch.rand(53)
    assert torch.equal(toy_model.animate(back, expr).means, toy_model.animate(avatar, expr).means)
    avatar.to_ply(tmp_path / "a.ply")
    assert (tmp_path / "a.ply").stat().st_size > len(avatar) * 4


def test_training_forward_under_bf16_autocast(toy_model):
    """Camera geometry and the Gaussian head stay fp32 under autocast; results are near fp32."""
    imgs, K, w2c = toy_inputs(2, b=1)
    expr = torch.rand(1, 53)
    with torch.no_grad():
        ref = toy_model(imgs, K, w2c, expr).gaussians[0]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = toy_model(imgs, K, w2c, expr).gaussians[0]
    assert low.means.dtype == torch.float32 and low.scales.dtype == torch.float32
    err = (low.means - ref.means).norm(dim=-1)  # metres; the depth range is 0.35
    assert err.mean() < 5e-3 and err.max() < 0.05, (float(err.mean()), float(err.max()))
    assert (low.opacities - ref.opacities).abs().mean() < 0.01


def _disc_on_background(v: int = 2) -> torch.Tensor:
    """``[v, 3, S, S]``: a random-coloured disc (radius 10 px) on ``BACKGROUND_RGB``, shifted per view."""
    gen = torch.Generator().manual_seed(3)
    yy, xx = torch.meshgrid(torch.arange(S).float(), torch.arange(S).float(), indexing="ij")
    imgs = torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1).repeat(v, 1, S, S)
    for i in range(v):
        disc = (yy - 15 - i) ** 2 + (xx - 14 + 2 * i) ** 2 <= 100
        imgs[i][:, disc] = 0.2 + 0.3 * torch.rand(3, int(disc.sum()), generator=gen)
    return imgs


def test_edge_weight_matches_brute_force_distance():
    from fastgha_core.model.gaussian_head import edge_weight, foreground_weight

    imgs = _disc_on_background(2)
    w = edge_weight(imgs, 3.0)
    assert w.shape == (2, S, S)
    pix = torch.stack(torch.meshgrid(torch.arange(S).float(), torch.arange(S).float(), indexing="ij"), -1).reshape(-1, 2)
    for i in range(2):
        bg = (foreground_weight(imgs[i]) < 0.5).reshape(-1)
        d = torch.cdist(pix, pix[bg]).min(dim=1).values.reshape(S, S)  # to the nearest background pixel centre
        assert_close(w[i], (d - 3.0).clamp(0, 1), atol=1e-5, rtol=0)
    assert float(w[0][15, 14]) == 1.0 and float(w[0][15, 14 + 9]) == 0.0  # centre kept, 1 px inside the rim faded
    assert float(w[0][0, 0]) == 0.0  # background itself
    assert torch.equal(edge_weight(imgs, 0.0), torch.ones(2, S, S))
    assert torch.equal(edge_weight(torch.full((1, 3, S, S), 0.3), 3.0), torch.ones(1, S, S))  # no background: nothing fades
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, H, W\]"):
        edge_weight(torch.zeros(S, S), 3.0)


def test_edge_source_index_takes_the_nearest_interior_pixel():
    from fastgha_core.model.gaussian_head import edge_source_index, edge_weight, foreground_weight

    imgs = _disc_on_background(2)
    idx = edge_source_index(imgs, 3.0)
    assert idx.shape == (2, S, S) and idx.dtype == torch.long
    pix = torch.stack(torch.meshgrid(torch.arange(S).float(), torch.arange(S).float(), indexing="ij"), -1).reshape(-1, 2)
    own = torch.arange(S * S)
    for i in range(2):
        fg = (foreground_weight(imgs[i]) >= 0.5).reshape(-1)
        bg_d = torch.cdist(pix, pix[~fg]).min(dim=1).values
        interior = bg_d >= 4.0
        band = fg & ~interior
        assert int(band.sum()) > 20 and int(interior.sum()) > 20
        src = idx[i].reshape(-1)
        assert torch.equal(src[~band], own[~band])  # interior and background keep their own pixel
        assert bool(interior[src[band]].all())  # outline pixels take an interior one ...
        got = (pix[band] - pix[src[band]]).norm(dim=1)
        best = torch.cdist(pix[band], pix[interior]).min(dim=1).values
        assert_close(got, best, atol=1e-5, rtol=0)  # ... the nearest
        assert bool((edge_weight(imgs[i], 3.0).reshape(-1)[band] < 1).all())
    assert torch.equal(edge_source_index(imgs, 0.0), own.view(S, S).expand(2, S, S))
    assert torch.equal(edge_source_index(torch.full((1, 3, S, S), 0.3), 3.0), own.view(1, S, S))  # no background
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, H, W\]"):
        edge_source_index(torch.zeros(S, S), 3.0)


def _edge_models(toy_model, **gcfg):
    out = []
    for kw in ({"edge_margin_px": 0.0}, gcfg):
        m = FastGHA(toy_config(gaussians=GaussianHeadConfig(feature_dim=8, prune_opacity=0.0, **kw)))
        m.load_state_dict(toy_model.state_dict())
        out.append(m.eval())
    return out


def test_reconstruct_recolours_gaussians_at_the_matte_outline(toy_model):
    from fastgha_core.model.gaussian_head import edge_source_index

    imgs = _disc_on_background(2)
    cams = orbit_cameras(2, width=S, height=S)
    off, on = _edge_models(toy_model, edge_margin_px=3.0, edge_mode="colour")
    a0, a1 = off.reconstruct(imgs, cams), on.reconstruct(imgs, cams)
    n = 2 * S * S
    c0, c1 = a0.gaussians.colors[:n], a1.gaussians.colors[:n]
    src = (edge_source_index(imgs, 3.0).reshape(2, -1) + torch.arange(2)[:, None] * S * S).reshape(-1)
    moved = src != torch.arange(n)
    assert int(moved.sum()) > 40
    assert torch.equal(c1, c0[src])  # each outline Gaussian takes its view's nearest interior colour
    assert not torch.equal(c1[moved], c0[moved]) and torch.equal(c1[~moved], c0[~moved])
    assert torch.equal(a1.gaussians.opacities, a0.gaussians.opacities) and torch.equal(a1.gaussians.means, a0.gaussians.means)
    with pytest.raises(ValueError, match=r"gaussians\.edge_mode must be one of \['colour', 'fade'\], got 'blur'"):
        _edge_models(toy_model, edge_margin_px=3.0, edge_mode="blur")  # the config refuses it (FastGHAConfig.validate)
    on.config.gaussians.edge_mode = "blur"  # set on a built model: reconstruct() still refuses it
    with pytest.raises(ValueError, match="edge_mode must be 'colour' or 'fade', got 'blur'"):
        on.reconstruct(imgs, cams)


def test_reconstruct_fades_gaussians_at_the_matte_outline(toy_model):
    from fastgha_core.model.gaussian_head import edge_weight

    imgs = _disc_on_background(2)
    cams = orbit_cameras(2, width=S, height=S)
    off, on = _edge_models(toy_model, edge_margin_px=3.0, edge_mode="fade")
    a0, a1 = off.reconstruct(imgs, cams), on.reconstruct(imgs, cams)
    o0, o1 = a0.gaussians.opacities[: 2 * S * S], a1.gaussians.opacities[: 2 * S * S]
    w = edge_weight(imgs, 3.0).reshape(-1)
    assert_close(o1, o0 * w)
    assert bool((o1[w == 0] == 0).all()) and bool((o0[w == 0] > 0).all())  # the outline band goes, ...
    inner = w == 1
    assert int(inner.sum()) > 100 and torch.equal(o1[inner], o0[inner])  # ... the interior is untouched
    assert torch.equal(a1.gaussians.means, a0.gaussians.means) and torch.equal(a1.gaussians.colors, a0.gaussians.colors)
