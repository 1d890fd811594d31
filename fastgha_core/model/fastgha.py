"""FastGHA: few-shot feed-forward reconstruction of a canonical Gaussian head + real-time deformation.

Pipeline (paper §3.2; one module per stage)::

    images [B,V,3,H,W] --SemanticEncoder--> F_dino [B*V,C_d,H/8,W/8]
                       --ColourEncoder----> F_enc  [B*V,4,H/8,W/8]
    cameras ----------- plucker_rays -----> P_cam  [B,V,6,H/8,W/8]
    tokens [B,V,C_d+4+6,H/8,W/8] --MultiViewTransformer--> [B,V,D,H/8,W/8]
      --GaussianDecoder--> raw maps [B,V,12+F,H,W] --GaussianHead--> canonical Gaussians (V*H*W per sample)
    canonical + expression --DeformationMLP--> (dxyz, drgb) --> deformed Gaussians

Entry points: ``forward`` (training), ``prepare`` + ``reconstruct`` (inference, no grad),
``animate`` (per frame, with the deformation MLP's first layer split), ``save_pretrained`` /
``from_pretrained`` / ``load_model``.
"""

from __future__ import annotations

import time
import copy
import json
import logging
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..cameras import Cameras, plucker_rays
from ..config import PRESETS, FastGHAConfig, get_preset
from ..constants import BACKGROUND_RGB
from ..gaussians import Gaussians
from .avatar import CanonicalAvatar
from .decoder import GaussianDecoder
from .deform import DeformationMLP
from .encoders import ColourEncoder, SemanticEncoder
from .gaussian_head import GaussianHead, GaussianLayout
from .transformer import MultiViewTransformer
from .viewblend import MAX_BLEND_VIEWS, ViewBlend, coverage_masks, view_depth_maps, view_directions

__all__ = ["FastGHA", "FastGHAOutput", "load_model", "ASSET_MODELS_DIR", "CONFIG_NAME", "WEIGHTS_NAME"]

log = logging.getLogger(__name__)

HAIR_CARVE_DILATE_PX = 1  # reconstruct(): the hair layer is carved by the inputs' mattes dilated by this many pixels (model/surface.py hair_carve_fractions)
HAIR_CARVE_MAX_UP = 0.5  # ... only vertices whose outward normal's up component is at most this (the top of the head, normals within 60 deg of up, keeps its fitted thickness: carved by all views, phone-5's pitch-down photo left out lost 12.28 -> 10.85 dB; mattes cut fine hair on top)
SHELL_CARVE_DILATE_PX = -2  # reconstruct(): the back-of-head shell is carved into the inputs' mattes eroded by 2 pixels: its discs (5.5 mm) reach beyond their centres (model/surface.py carve_into_mattes; video-6 at its own cameras: dilated by 1 23.89 dB, eroded by 1 23.98, by 2 24.02, the bald shell 24.03)
MIRROR_UNDER_CHIN_MARGIN_M = 0.0  # reconstruct(), gaussians.mirror_under_below_chin: the mirrored Gaussians at least this far below the tracked chin are drawn under the others (docs/model-card-log.md "Skin and off-colour smears over the shoulders")
OFF_HEAD_HULL_COLLAR = False  # reconstruct() with gaussians.off_head_hull: also move the mesh's own pixels below its neck ring whose point is outside the other views' hull (model/surface.py off_head_on_hull)
OFF_HEAD_HULL_DILATE_PX = 2  # ... the other views' mattes dilated by this many pixels
OFF_HEAD_HULL_FREE_TOL_M = None  # ... and, when set (metres), the space in front of the head each other view sees is empty (up to this tolerance)
FLOW_REGISTER_SIGMA_PX = 4.0  # reconstruct() with gaussians.flow_register: the flow's smoothing, pixels at an image side of 256 (model/flowreg.py smooth_flow)
FLOW_REGISTER_FALLOFF_PX = 6.0  # ... its fade to zero beyond the measured pixels, pixels at a side of 256
FLOW_REGISTER_FACE_ONLY = False  # ... measured on the bare face only (SurfaceDepth.face_hit), not on hair, ears and neck
FLOW_REGISTER_MODE = "chain"  # ... "chain" (each view onto its neighbour, from the most frontal one) or "mean" (each halfway towards every view that sees its points; model/flowreg.py register_views)
OFF_HEAD_BEHIND_M = 0.02  # reconstruct() with gaussians.off_head_draw="behind": metres the off-head pixels move back along their ray (model/surface.py off_head_draw_flags)
OFF_HEAD_COVER_TOL_M = 0.01  # ... "drop" / "cover_sharp": metres in front of another view's head a point must lie to count as a smear

ASSET_MODELS_DIR = Path(__file__).resolve().parent.parent / "assets" / "models"
CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"


@dataclass
class FastGHAOutput:
    """What the training losses need, one entry per sample.

    Attributes:
        gaussians: deformed Gaussians (target expression applied, features kept), ready to render.
        canonical: the canonical Gaussians before deformation.
        view_depth: ``[B, V, H, W]`` each input pixel's Gaussian's distance (metres) from its view's
            camera centre, i.e. the depth along the pixel's ray (for ``LossConfig.w_depth_smooth``).
    """

    gaussians: list[Gaussians]
    canonical: list[Gaussians]
    view_depth: Tensor | None = None


def _apply_deformation(g: Gaussians, dxyz: Tensor, drgb: Tensor) -> Gaussians:
    """Canonical ``g`` with offsets ``dxyz``/``drgb [N, 3]`` applied (colours stay in [0, 1])."""
    return g.replace(means=g.means + dxyz, colors=(g.colors + drgb).clamp(0.0, 1.0))


def _combine(g: Gaussians, dxyz: Tensor, drgb: Tensor, prior_d: Tensor | None, n_int: int, gate: Tensor | None, trim: bool = False, shade: Tensor | None = None, rot: Tensor | None = None) -> Gaussians:
    """Deformed ``g`` from the MLP's ``dxyz``/``drgb [N_rec, 3]`` (first ``N - n_int`` Gaussians), the
    prior's displacement ``[N, 3]`` (or None), per-Gaussian opacity factors ``gate [N]`` (or None) and
    the prior's expression shading ``shade [N]`` (or None): the reconstructed Gaussians' colour factor.

    ``trim``: drop the trailing interior Gaussians whose gate is 0 (the interior is ordered back-of-head
    shell (ungated), lip seam (shown while the lips are closed), mouth, left lid, right lid, so a neutral
    frame renders no mouth or lid Gaussians). ``rot [N, 4]`` (or None): the prior's surface rotation
    (``PriorRuntime.rotation``), applied after each Gaussian's own rotation."""
    if prior_d is None and n_int == 0 and gate is None:
        return _apply_deformation(g, dxyz, drgb)
    if trim and n_int and gate is not None:
        n_rec = len(g) - n_int
        nz = torch.nonzero(gate[n_rec:] > 0)
        end = n_rec + (int(nz[-1]) + 1 if len(nz) else 0)
        if end < len(g):
            g, gate, n_int = g[:end], gate[:end], end - n_rec
            prior_d = None if prior_d is None else prior_d[:end]
            rot = None if rot is None else rot[:end]
    if rot is not None:
        from .gaussian_head import quaternion_multiply

        g = g.replace(quats=quaternion_multiply(rot, g.quats))
    n_rec = len(g) - n_int
    if shade is not None:
        rec_colors = ((g.colors[:n_rec] + drgb).clamp(0.0, 1.0) * shade[:n_rec, None]).clamp(0.0, 1.0)
    else:
        rec_colors = (g.colors[:n_rec] + drgb).clamp(0.0, 1.0)
    if prior_d is None:
        prior_d = dxyz.new_zeros(len(g), 3)
    op = g.opacities if gate is None else g.opacities * gate
    if n_int:
        means = g.means + torch.cat([prior_d[:n_rec] + dxyz, prior_d[n_rec:]])
        colors = torch.cat([rec_colors, g.colors[n_rec:]])
        return g.replace(means=means, colors=colors, opacities=op)
    return g.replace(means=g.means + prior_d + dxyz, colors=rec_colors, opacities=op)


class FastGHA(nn.Module):
    """The reconstruction network and the deformation MLP.

    Args:
        config: a ``FastGHAConfig`` (copied; ``get_preset("tiny")`` etc.).
        dino_weights: optional local ``DINOv3ViTModel`` folder; loaded and frozen.
        vae_weights: optional local ``AutoencoderKL`` folder; its encoder is loaded and frozen, and
            its decoder initialises the Gaussian decoder (``config.decoder.init_from_vae``).
    """

    def __init__(self, config: FastGHAConfig, dino_weights: str | Path | None = None, vae_weights: str | Path | None = None):
        super().__init__()
        config = copy.deepcopy(config)
        config.validate()
        self.config = config
        fdim = config.gaussians.feature_dim
        self.layout = GaussianLayout(fdim)
        self.semantic = SemanticEncoder(config.dino)  # shares config.dino (records `frozen`)
        self.colour = ColourEncoder(config.vae)
        self.transformer = MultiViewTransformer(config.token_channels, config.transformer)
        self.decoder = GaussianDecoder(config.transformer.hidden_size, self.layout, config.decoder)
        self.head = GaussianHead(config.gaussians)
        self.deform = DeformationMLP(fdim, config.expression_dim, config.deform)
        if dino_weights is not None or vae_weights is not None:
            self.load_pretrained_encoders(dino_weights, vae_weights)

    # ------------------------------------------------------------ weights
    def load_pretrained_encoders(self, dino_weights: str | Path | None = None, vae_weights: str | Path | None = None) -> None:
        """Load local Hugging Face-format encoder folders and freeze those encoders."""
        if dino_weights is not None:
            self.semantic.load_pretrained(dino_weights)
        if vae_weights is not None:
            dec_state = self.colour.load_pretrained(vae_weights)
            if self.config.decoder.init_from_vae:
                self.decoder.load_vae_decoder(dec_state)

    def save_pretrained(self, folder: str | Path) -> None:
        """Write ``config.json`` + ``model.safetensors`` into ``folder``."""
        from safetensors.torch import save_file

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / CONFIG_NAME).write_text(json.dumps(self.config.to_dict(), indent=2) + "\n")
        state = {k: v.detach().to("cpu").contiguous() for k, v in self.state_dict().items()}
        save_file(state, str(folder / WEIGHTS_NAME), metadata={"format": "pt", "fastgha_model": self.config.name})

    @staticmethod
    def read_config(folder: str | Path) -> FastGHAConfig:
        """The validated ``FastGHAConfig`` of a model folder written by ``save_pretrained``, without
        its weights. Raises ``ValueError`` naming the file when either file is missing, the JSON does
        not parse, or a field is unknown or out of its range (``FastGHAConfig.validate``)."""
        folder = Path(folder)
        cfg_file, w_file = folder / CONFIG_NAME, folder / WEIGHTS_NAME
        if not cfg_file.is_file() or not w_file.is_file():
            raise ValueError(f"model folder {str(folder)!r} must contain {CONFIG_NAME} and {WEIGHTS_NAME} (written by save_pretrained)")
        try:
            return FastGHAConfig.from_dict(json.loads(cfg_file.read_text()))
        except json.JSONDecodeError as e:
            raise ValueError(f"{cfg_file}: does not parse as JSON: {e}") from None
        except (ValueError, TypeError) as e:  # validate(): the field and its allowed range
            raise ValueError(f"{cfg_file}: {e}") from None

    @classmethod
    def from_pretrained(cls, folder: str | Path, device: Any = "cpu") -> "FastGHA":
        """Load a folder written by ``save_pretrained`` (eval mode); its config is checked by ``read_config``."""
        from safetensors.torch import load_file

        cfg = cls.read_config(folder)
        cfg_file, w_file = Path(folder) / CONFIG_NAME, Path(folder) / WEIGHTS_NAME
        model = cls(cfg)
        state = load_file(str(w_file), device="cpu")
        missing, unexpected = model.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise ValueError(f"{w_file} does not match {cfg_file}: missing {missing[:5]}, unexpected {unexpected[:5]}")
        return model.to(device).eval()

    # ------------------------------------------------------------ info
    @property
    def expression_space(self):
        """The model's ``fastgha_core.expressions.ExpressionSpace``."""
        from ..expressions import get_space

        return get_space(self.config.expression_space)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per module (``dino_vit`` is the pretrained backbone, ``dino_fusion`` the new convs)."""
        count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
        out = {
            "dino_vit": count(self.semantic.vit),
            "dino_fusion": count(self.semantic) - count(self.semantic.vit),
            "vae_encoder": count(self.colour),
            "transformer": count(self.transformer),
            "decoder": count(self.decoder),
            "deform": count(self.deform),
        }
        out["total"] = sum(out.values())
        out["trainable"] = sum(p.numel() for p in self.parameters() if p.requires_grad)
        return out

    # ------------------------------------------------------------ reconstruction
    def forward_gaussians(self, images: Tensor, cameras: Cameras, ray_depth: Tensor | None = None) -> list[Gaussians]:
        """Canonical Gaussians per sample.

        Args:
            images: ``[B, V, 3, H, W]`` in [0, 1], matted on ``BACKGROUND_RGB``.
            cameras: batch ``[B, V]`` describing the ``W x H`` images.
            ray_depth: optional ``[B, V, H, W]`` distances (metres) along each pixel's ray that replace
                the predicted depth (``model/surface.py``).
        Returns:
            ``B`` canonical ``Gaussians`` of ``V*H*W`` points with features.
        """
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images must have shape [B, V, 3, H, W], got {list(images.shape)}")
        b, v, _, h, w = images.shape
        if tuple(cameras.batch_shape) != (b, v) or (cameras.width, cameras.height) != (w, h):
            raise ValueError(
                f"cameras must have batch shape [{b}, {v}] and size {w}x{h}, "
                f"got {list(cameras.batch_shape)} and {cameras.width}x{cameras.height}"
            )
        if h % 8 or w % 8:
            raise ValueError(f"image size must be divisible by 8, got {w}x{h}")
        flat = images.flatten(0, 1)  # [B*V, 3, H, W]
        f_dino = self.semantic(flat)  # [B*V, C_d, H/8, W/8]
        f_enc = self.colour(flat)  # [B*V, 4, H/8, W/8]
        with torch.autocast(device_type=images.device.type, enabled=False):  # camera geometry in fp32
            p_cam = plucker_rays(cameras.to(dtype=torch.float32), h // 8, w // 8)  # [B, V, 6, H/8, W/8]
        f_dino, f_enc = f_dino.unflatten(0, (b, v)), f_enc.unflatten(0, (b, v))
        tokens = torch.cat([f_dino, f_enc.to(f_dino.dtype), p_cam.to(f_dino.dtype)], dim=2)
        x = self.transformer(tokens)  # [B, V, D, H/8, W/8]
        maps = self.decoder(x)  # [B, V, 12+F, H, W]
        return self.head(maps, cameras, images, ray_depth)

    def forward(self, images: Tensor, K: Tensor, w2c: Tensor, expression: Tensor, input_expressions: Tensor | None = None) -> FastGHAOutput:
        """Training forward.

        Args:
            images: ``[B, V, 3, H, W]`` input views in [0, 1].
            K: ``[B, V, 3, 3]`` intrinsics of the input images; w2c: ``[B, V, 4, 4]``.
            expression: ``[B, E]`` target expression per sample.
            input_expressions: ``[B, V, E]`` expressions of the input views (optional): with the
                expression prior they are undone in the canonical head, as ``reconstruct`` does.
        """
        if images.ndim != 5:
            raise ValueError(f"images must have shape [B, V, 3, H, W], got {list(images.shape)}")
        b = images.shape[0]
        e = self.config.expression_dim
        if expression.shape != (b, e):
            raise ValueError(f"expression must have shape [B={b}, E={e}], got {list(expression.shape)}")
        cams = Cameras(K, w2c, images.shape[-1], images.shape[-2])
        canonical = self.forward_gaussians(images, cams)
        v = images.shape[1]
        h, w = images.shape[-2:]
        view_depth = torch.stack([(g.means.view(v, h, w, 3) - cams.centers[i].to(g.means)[:, None, None]).norm(dim=-1) for i, g in enumerate(canonical)])
        deformed = []
        for i, (g, z) in enumerate(zip(canonical, expression)):
            if self.config.deform.prior:
                if input_expressions is not None:
                    vi = torch.arange(v, device=g.means.device).repeat_interleave(len(g) // v)  # view-major, unpruned
                    g, binding, n_int = self.build_prior(g, vi, input_expressions[i])
                else:
                    g, binding, n_int = self.build_prior(g)
                canonical[i] = g
                rt = self._runtime(binding, g, n_int)
                gate = self._gate(z, rt)
                n_rec = len(g) - n_int
                dxyz, drgb = self.deform(g.features[:n_rec], g.means[:n_rec], z)
                rot = rt.rotation(z) if rt.rotate_on else None
                deformed.append(_combine(g, dxyz, drgb, rt.displacement(z), n_int, gate, shade=rt.shading(z) if rt.shading_on else None, rot=rot))
            else:
                dxyz, drgb = self.deform(g.features, g.means, z)
                deformed.append(_apply_deformation(g, dxyz, drgb))
        return FastGHAOutput(gaussians=deformed, canonical=canonical, view_depth=view_depth)

    # ------------------------------------------------------------ expression prior (issue 16)
    def head_basis(self):
        """The ``model.prior.HeadBasis`` of this model's expression space (FLAME needs a user file)."""
        from .prior import load_basis

        return load_basis(self.config.expression_space, self.config.deform.flame_model)

    def _runtime(self, binding, g: Gaussians | None = None, n_int: int = 0):
        """The binding's ``PriorRuntime``; with the avatar's Gaussians ``g`` (the last ``n_int`` not
        reconstructed) its expression shading takes the light baked into their colours
        (``prior.estimate_light``), else the generic light."""
        from .prior import PriorRuntime, estimate_light

        basis = self.head_basis()
        light = None
        if g is not None and self.config.deform.prior_shading:
            n = len(g) - n_int
            light = estimate_light(g.colors[:n], g.opacities[:n], binding, basis)
        return PriorRuntime(binding, basis, device=binding.vertex_ids.device, shading=self.config.deform.prior_shading, rotate=self.config.deform.prior_rotate, light=light)

    @staticmethod
    def _gate(z: Tensor, rt) -> Tensor | None:
        """Per-Gaussian opacity factors ``[N]`` (``[B, N]``) for ``z`` (None when nothing is gated)."""
        from .prior import opacity_factors

        return opacity_factors(z, rt.basis, rt.group_index) if rt.gated else None

    def build_prior(self, g: Gaussians, view_index: Tensor | None = None, view_expressions: Tensor | None = None, head_fit=None, shell_fit=None, anchor: bool = False):
        """Fit the head surface to canonical ``g``, bind every Gaussian, optionally undo the input
        photos' expressions, and append the mouth interior. The fit and the binding use the neutral
        positions the avatar is drawn at (centres + the deformation MLP's residual at the neutral
        expression); with ``view_expressions`` they are redone on the neutralised cloud.

        Args:
            g: canonical Gaussians (N).
            view_index: ``[N]`` input view each Gaussian came from (with ``view_expressions``).
            view_expressions: ``[V, E]`` expression of each input photo (known or tracked): its prior
                displacement is subtracted from the Gaussians of that view (a neutral canonical head).
            head_fit: a ``prior.HeadFit`` to bind to (the tracked head, ``HeadSurface.head_fit``)
                instead of fitting the head surface to the Gaussians.
            shell_fit: a ``prior.HeadFit`` to lay the back-of-head shell on instead of the one bound to
                (the tracked head with its scalp laid out by the hair thickness, ``HeadSurface.head_fit(basis, hair_m)``).
            anchor: the avatar will be animated with the MLP's residual relative to each view's
                expression (``residual_anchor``): the neutral positions are then the centres plus
                ``MLP(neutral) - MLP(z_view)`` (needs ``view_index`` and ``view_expressions``).
        Returns:
            ``(gaussians, binding, num_interior)``; the returned Gaussians keep ``g``'s autograd graph
            (means are shifted by a constant when neutralising; the appended shell and interior are
            constants), so a training forward's losses reach the reconstruction network. (Until
            2026-11-30 this method ran entirely under ``no_grad``: with the prior on, training updated
            the deformation MLP only.)
        """
        with torch.no_grad():
            fit, binding, means, shift, back = self._prior_binding(g, view_index, view_expressions, head_fit, anchor)
        if shift is not None:
            g = g.replace(means=g.means - shift.to(g.means.device, g.means.dtype))
            if back is not None:  # and its surface rotation, so a frame's rotation starts from neutral
                from .gaussian_head import quaternion_multiply

                g = g.replace(quats=quaternion_multiply(back.to(g.quats.device, g.quats.dtype), g.quats))
        with torch.no_grad():
            extra, binding, n_int = self._prior_extras(g, fit, binding, means if shift is None else means - shift, shell_fit)
        if extra is not None:
            g = Gaussians.concat([g, extra.to(g.means.device, g.means.dtype)])
        return g, binding, n_int

    def _prior_binding(self, g: Gaussians, view_index: Tensor | None, view_expressions: Tensor | None, head_fit, anchor: bool = False):
        """``build_prior``'s fit and binding (no autograd): ``(fit, binding, means, shift, back)``;
        ``shift [N, 3]`` (None without ``view_expressions``) is subtracted from the means, ``back
        [N, 4]`` (None unless ``prior_rotate``) pre-multiplies the quaternions."""
        from .lids import show_closed_lids
        from .prior import bind, fit_head, generic_fit, hide_open_lips, open_mouth_views

        basis = self.head_basis()
        means = g.means.detach().float().cpu()
        solid = g.opacities.detach().cpu() > 0.2
        # Fit and bind where each Gaussian is drawn at the neutral expression: canonical centre + the
        # MLP's residual there (3-4 mm median on held-out reconstructions), not the bare centre. On 10
        # held-out subjects this raised the mouthSmile response 0.35 -> 0.46 and the eyeBlink one
        # -0.19 -> 0.04 (jawOpen 0.75 -> 0.77).
        z0 = torch.as_tensor(self.expression_space.neutral(), dtype=g.means.dtype, device=g.means.device)
        means = means + self.deform(g.features.detach(), g.means.detach(), z0)[0].detach().float().cpu()
        if anchor and view_index is not None and view_expressions is not None:  # drawn as animate() will: minus MLP(z_view)
            f, x, dev = g.features.detach(), g.means.detach(), self.device
            means = means - self._offsets_at_views(view_index, view_expressions, lambda sel, z: self.deform(f[sel].to(dev), x[sel].to(dev), z)[0]).cpu()
        if head_fit is not None:
            fit = head_fit
        else:
            try:
                fit = fit_head((means[solid] if int(solid.sum()) >= 100 else means).numpy(), basis)
            except (ValueError, np.linalg.LinAlgError):  # too few Gaussians or a degenerate cloud: the generic head
                fit = generic_fit(basis)
        # on a tracked head, Gaussians inside the fitted mouth are photos' teeth: they fade as it opens
        binding = bind(means, fit, basis, tuple(self.config.deform.prior_fade), hide_inside=head_fit is not None)
        shift = back = None
        if view_expressions is not None:
            if view_index is None or view_index.shape != (len(g),):
                raise ValueError(f"build_prior: view_index must have shape [{len(g)}] with view_expressions")
            ve = torch.as_tensor(view_expressions, dtype=torch.float32).cpu()
            vi = view_index.cpu().long()
            shift = self._runtime(binding).displacement(ve)[vi, torch.arange(len(g))]  # [N, 3]
            if head_fit is None and float(ve.abs().max()) > 0 and int(solid.sum()) >= 100:
                # refit and rebind on the neutralised cloud: an open mouth in an input photo otherwise
                # pulls the neutral head's fit (and so the lip seam every Gaussian binds across)
                neutral = (means - shift).numpy()
                try:
                    fit = fit_head(neutral[solid.numpy()], basis)
                    binding = bind(neutral, fit, basis, tuple(self.config.deform.prior_fade))
                    shift = self._runtime(binding).displacement(ve)[vi, torch.arange(len(g))]
                except (ValueError, np.linalg.LinAlgError):
                    pass
            if self.config.deform.prior_rotate:
                rt = self._runtime(binding)
                back = rt.rotation(ve)[vi, torch.arange(len(g))] * torch.tensor([1.0, -1.0, -1.0, -1.0])  # [N, 4] inverse
            # lips of open-mouthed photos (their teeth and gap undone onto the closed lips) fade out as the mouth opens
            binding = hide_open_lips(binding, means - shift, vi, open_mouth_views(ve, basis), basis)
            # closed-eyed photos' lids appear only as the avatar's lids close (model/lids.py)
            binding = show_closed_lids(binding, means, vi, ve, fit, basis)
        return fit, binding.to(g.means.device), means, shift, back

    def _prior_extras(self, g: Gaussians, fit, binding, drawn: Tensor, shell_fit=None):
        """``build_prior``'s back-of-head shell, chin shell and mouth interior for the (neutralised) ``g``:
        ``(extra Gaussians or None, binding, num_interior)``; ``drawn`` is where ``g`` is drawn at the
        neutral expression."""
        from .prior import (PriorBinding, back_shell, back_shell_vertices, cheek_shell, cheek_shell_vertices, chin_shell, chin_shell_vertices, face_shell,
                            face_shell_vertices, interior_inset, mouth_interior)

        basis = self.head_basis()
        dev = g.means.device
        g = g.detach()
        parts, n_int = [], 0
        if self.config.deform.back_shell and len(back_shell_vertices(basis)):
            # ungated, so first: the gated interior after it stays a trailing run that frames trim
            gs, bs = back_shell(fit if shell_fit is None else shell_fit, basis, g.features.shape[1], avatar=g)
            parts.append(gs.to(dev, g.means.dtype))
            binding = PriorBinding.concat(binding, bs.to(dev))
            n_int = len(gs)
        if self.config.deform.chin_shell and len(chin_shell_vertices(basis)):
            # also ungated, after the back shell (``_shell_count``); on the bound fit: it moves with the jaw
            gs, bs = chin_shell(fit, basis, g.features.shape[1], avatar=g)
            parts.append(gs.to(dev, g.means.dtype))
            binding = PriorBinding.concat(binding, bs.to(dev))
            n_int += len(gs)
        if self.config.deform.cheek_shell and len(cheek_shell_vertices(basis)):
            # ungated too, after the chin shell: skin under the cheeks, in front of the mouth interior
            gs, bs = cheek_shell(fit, basis, g.features.shape[1], avatar=g)
            parts.append(gs.to(dev, g.means.dtype))
            binding = PriorBinding.concat(binding, bs.to(dev))
            n_int += len(gs)
        if len(face_shell_vertices(basis, self.config.deform.face_shell)):
            # ungated too, after the cheek shell: skin under the face (``_shell_count``)
            gs, bs = face_shell(fit, basis, g.features.shape[1], avatar=g, region=self.config.deform.face_shell)
            parts.append(gs.to(dev, g.means.dtype))
            binding = PriorBinding.concat(binding, bs.to(dev))
            n_int += len(gs)
        if self.config.deform.mouth_interior and len(basis.interior_vertices):
            # the interior behind the avatar's own lips, which sit a few mm behind the fitted ones
            inset = interior_inset(drawn, fit, basis, g.opacities)
            gi, bi = mouth_interior(fit, basis, g.features.shape[1], avatar=g, inset=inset, drawn=drawn)
            parts.append(gi.to(dev, g.means.dtype))
            binding = PriorBinding.concat(binding, bi.to(dev))
            n_int += len(gi)
        return (Gaussians.concat(parts) if parts else None), binding, n_int

    @torch.inference_mode()
    def static_gaussians(self, avatar: CanonicalAvatar) -> Gaussians:
        """The canonical Gaussians without any deformation, gated Gaussians (mouth interior, closed
        lids) as at the neutral expression: the "static head" baseline."""
        g = avatar.gaussians.to(self.device)
        if not (self.config.deform.prior and avatar.prior is not None):
            return g
        rt = self._runtime(avatar.prior.to(self.device))
        gate = self._gate(torch.as_tensor(self.expression_space.neutral(), dtype=torch.float32, device=self.device), rt)
        return g if gate is None else g.replace(opacities=g.opacities * gate)

    def attach_prior(self, avatar: CanonicalAvatar) -> CanonicalAvatar:
        """Give an avatar made without the prior (an older file) its binding and mouth interior, in place."""
        if avatar.prior is None and self.config.deform.prior:
            g, binding, n_int = self.build_prior(avatar.gaussians[: avatar.num_reconstructed])
            avatar.gaussians, avatar.prior, avatar.num_interior = g, binding, n_int
            avatar.deform_cache = avatar.prior_runtime = None
        return avatar

    def prepare(
        self,
        images: Tensor | Sequence[Tensor],
        cameras: Cameras | Sequence[Cameras],
        masks: Tensor | Sequence[Tensor | None] | None = None,
    ) -> tuple[Tensor, Cameras]:
        """Matte, centre-crop to a square and resize to the model's input size, adjusting K.

        Args:
            images: ``[V, 3, H, W]`` or a list of ``[3, H_i, W_i]``; float in [0, 1] or uint8.
            cameras: ``Cameras`` batch ``[V]`` or a list of single cameras matching each image's size.
            masks: optional ``[V, H, W]`` / list of ``[H_i, W_i]`` or ``[1, H_i, W_i]`` alpha in [0, 1]
                (uint8 -> /255); the background becomes ``BACKGROUND_RGB``.
        Returns:
            images ``[V, 3, S, S]`` and ``Cameras`` ``[V]`` of size ``S x S``.
        """
        imgs = list(images.unbind(0)) if isinstance(images, Tensor) and images.ndim == 4 else list(images)
        if isinstance(cameras, Cameras):
            flat = cameras.flatten()
            cams = [flat[i] for i in range(len(flat.K))]
        else:
            cams = [c.flatten()[0] for c in cameras]
        if len(imgs) != len(cams):
            raise ValueError(f"prepare: got {len(imgs)} images but {len(cams)} cameras")
        if masks is None:
            mlist: list[Tensor | None] = [None] * len(imgs)
        else:
            mlist = list(masks.unbind(0)) if isinstance(masks, Tensor) and masks.ndim >= 3 and masks.shape[0] == len(imgs) else list(masks)
            if len(mlist) != len(imgs):
                raise ValueError(f"prepare: got {len(imgs)} images but {len(mlist)} masks")
        s = self.config.input_size
        bg = torch.tensor(BACKGROUND_RGB, dtype=torch.float32).view(3, 1, 1)
        out_i, out_c = [], []
        for i, (img, cam, m) in enumerate(zip(imgs, cams, mlist)):
            img = torch.as_tensor(img)
            if img.ndim != 3 or img.shape[0] != 3:
                raise ValueError(f"prepare: image {i} must have shape [3, H, W], got {list(img.shape)}")
            img = img.float() / 255.0 if img.dtype == torch.uint8 else img.float()
            h, w = img.shape[1:]
            if (cam.width, cam.height) != (w, h):
                raise ValueError(f"prepare: camera {i} describes a {cam.width}x{cam.height} image, but image {i} is {w}x{h}")
            if m is not None:
                m = torch.as_tensor(m)
                m = m.float() / 255.0 if m.dtype == torch.uint8 else m.float()
                m = m.reshape(m.shape[-2:]) if m.ndim == 3 and m.shape[0] == 1 else m
                if tuple(m.shape) != (h, w):
                    raise ValueError(f"prepare: mask {i} must have shape [{h}, {w}], got {list(m.shape)}")
                img = img * m + bg * (1.0 - m)
            side = min(h, w)
            left, top = (w - side) // 2, (h - side) // 2
            img = img[:, top : top + side, left : left + side]
            cam = cam.crop(left, top, side, side)
            if side != s:
                img = F.interpolate(img[None], size=(s, s), mode="bilinear", antialias=True, align_corners=False)[0]
                cam = cam.resize(s, s)
            out_i.append(img.clamp(0.0, 1.0))
            out_c.append(cam)
        return torch.stack(out_i), Cameras.stack(out_c)

    @torch.no_grad()
    def reconstruct(self, images: Tensor, cameras: Cameras, expressions: Tensor | None = None, surface=None, surface_mode: str = "replace") -> CanonicalAvatar:
        """Canonical avatar from ``images [V, 3, S, S]`` in [0, 1] and ``cameras [V]`` of size ``S x S``.

        ``S`` is ``config.input_size`` and ``1 <= V <= config.max_views``. Other sizes raise a
        ``ValueError``: use ``prepare()`` to crop and resize. Gaussians with opacity below
        ``config.gaussians.prune_opacity`` are dropped, after the Gaussians of pixels within
        ``config.gaussians.edge_margin_px`` of their view's background take the colour of the
        nearest pixel further in (``edge_mode="colour"``, the default) or are faded out
        (``"fade"``; ``gaussian_head.edge_weight``): matte-outline pixels are part wall. With the expression prior
        (``config.deform.prior``), ``expressions [V, E]`` (each photo's known or tracked expression,
        optional) are undone so the canonical head is neutral, and the avatar gets its head-surface
        binding and mouth interior.

        ``surface`` (a ``model.surface.HeadSurface`` of the ``V`` views, from tracking) puts every
        pixel's Gaussian on the tracked head along its ray instead of the predicted depth, and the
        expression prior binds to that head; its expressions are the photos' own unless
        ``expressions`` is given. See ``model/surface.py`` for why and what it changes.
        ``surface_mode``: ``"replace"`` (every pixel from the surface, ``surface_ray_depth``) or
        ``"blend"`` (the bare face from the surface, the rest the network's depth joined to it,
        ``surface.blend_network_depth``). On a surface, each view's own Gaussians are also made
        opaque enough that the avatar covers that view's matte from its camera
        (``config.gaussians.coverage_target``, ``model/coverage.py``; with
        ``coverage_surface_only=False`` on the network's depth as well), and with ``"replace"`` the
        scalp is laid out by a hair thickness fitted to the inputs' mattes
        (``config.gaussians.hair_fit``, ``surface.fit_hair_thickness``), and with
        ``config.gaussians.off_head_hull`` (off by default) the pixels off the head move onto the
        visual hull of the other inputs' mattes (``surface.off_head_on_hull``); with ``config.gaussians.off_head_smooth > 0`` (0.11 by default) the
        off-head pixels' distances, the nearest head pixel's, are relaxed along image columns between
        the head's (``surface.smooth_off_head_depth``: their steps opened slits through long hair in other
        views), the pixels ``off_head_behind_ears`` placed and those beside the head's outline
        (``off_head_smooth_hold``) held; with ``config.gaussians.off_head_extrude_m > 0`` (0.10 by
        default) the hair-coloured ones beside the head also get copies further back along their rays,
        inside the other inputs' mattes (``surface.off_head_extrusion``), appended after the
        pixel-aligned Gaussians and drawn under the others; with
        ``config.gaussians.off_head_draw="under"`` (the default) the off-head pixels' Gaussians are
        recorded (``ViewBlend.under``) and drawn under the others in every frame
        (``viewblend.push_under``; other modes: ``surface.off_head_draw_flags``); with
        ``config.gaussians.grazing_stretch > 0`` (0.5 by default) the Gaussians of pixels that see the head
        at a grazing angle (the cheek and the side of the head in a frontal photo) are lengthened
        along it to cover their patch of skin (``surface.stretch_to_patches``), except on the brows,
        eyes, nose and mouth (``grazing_keep_features_mm``, ``surface.away_from_face_features``) and,
        with ``grazing_edge_px > 0``, only just behind an occluding edge (``surface.behind_occluding_edges``).
        On a surface (or everywhere with ``config.gaussians.view_blend_surface_only=False``) the
        avatar also records each reconstructed Gaussian's source view and which input views see its
        point (``avatar.view_blend``, ``model/viewblend.py``) for view-dependent frames. With
        ``config.gaussians.mirror_views`` (on by default), an ict53 model and ``surface_mode="replace"``, the input views turned by
        at least ``mirror_min_yaw_deg`` also add their left-right mirror images as virtual views of the
        unseen side of the head, after the real views' Gaussians (``model/mirror.py``); with
        ``gaussians.mirror_under_below_chin`` those of them lower than the tracked chin (the mirrored neck
        and torso, which are not symmetric about a turned head) are drawn under the others in every
        frame (``ViewBlend.under``, ``surface.below_chin``). On a surface in
        ``"replace"`` mode the fitted hair thickness is thinned per vertex where it would stand out
        beyond an input's matte (``gaussians.hair_carve``, ``surface.hair_carve_fractions``), the
        back-of-head shell lies under that hair (``shell_on_hair``) and inside every input's matte
        (``shell_carve``, ``surface.carve_into_mattes``), and a real view's Gaussians whose colour the
        view that sees their point most head-on contradicts are drawn only near their own camera
        (``head_on_colour_tol``, ``viewblend.contradicted_by_head_on_view``, ``ViewBlend.sharp``).
        With ``config.gaussians.stereo_depth_mm > 0`` (off by default) in ``"replace"`` mode with two or
        more views, each view's pixels on the tracked head move along their rays, within that many
        millimetres of the surface, to where the other photos agree with them (``model/stereo.py``).
        """
        s, vmax = self.config.input_size, self.config.max_views
        hint = "use model.prepare(images, cameras) to crop/resize them"
        if not isinstance(images, Tensor) or images.ndim != 4 or tuple(images.shape[1:]) != (3, s, s):
            shape = list(images.shape) if isinstance(images, Tensor) else type(images).__name__
            raise ValueError(f"reconstruct: images must have shape [V, 3, {s}, {s}] for model {self.config.name!r}, got {shape}; {hint}")
        v = images.shape[0]
        if not 1 <= v <= vmax:
            raise ValueError(f"reconstruct: expected 1 to {vmax} views, got {v}")
        if not images.is_floating_point():
            raise ValueError(f"reconstruct: images must be float in [0, 1], got {images.dtype}; {hint}")
        lo, hi = float(images.min()), float(images.max())
        if lo < -1e-3 or hi > 1 + 1e-3:
            raise ValueError(f"reconstruct: images must lie in [0, 1], got values in [{lo:.3g}, {hi:.3g}]")
        if not isinstance(cameras, Cameras):
            raise ValueError(f"reconstruct: cameras must be a Cameras batch [V], got {type(cameras).__name__}")
        if tuple(cameras.batch_shape) != (v,) or (cameras.width, cameras.height) != (s, s):
            raise ValueError(
                f"reconstruct: cameras must have batch shape [{v}] and size {s}x{s}, got "
                f"{list(cameras.batch_shape)} and {cameras.width}x{cameras.height}; {hint}"
            )
        if expressions is not None:
            expressions = torch.as_tensor(expressions, dtype=torch.float32)
            if tuple(expressions.shape) != (v, self.config.expression_dim):
                raise ValueError(f"reconstruct: expressions must have shape [{v}, {self.config.expression_dim}], got {list(expressions.shape)}")
        ray_depth = head_fit = shell_fit = None
        if surface is not None:
            from .surface import surface_ray_depth

            if len(surface) != v:
                raise ValueError(f"reconstruct: surface has {len(surface)} views but {v} images were given")
            if surface_mode not in ("replace", "blend"):
                raise ValueError(f"reconstruct: surface_mode must be 'replace' or 'blend', got {surface_mode!r}")
            hair = 0.0
            if self.config.gaussians.hair_fit and surface_mode == "replace":  # the head model is bald (model/surface.py)
                from .gaussian_head import foreground_weight
                from .surface import fit_hair_thickness

                hair = fit_hair_thickness(surface, cameras, foreground_weight(images.float()))
                if self.config.gaussians.hair_carve and hair > 0:  # thinner where the photos' outlines say so (model/surface.py)
                    from .surface import hair_carve_fractions

                    hair = hair * hair_carve_fractions(surface, cameras.to(dtype=torch.float32), foreground_weight(images.float()), hair, HAIR_CARVE_DILATE_PX, HAIR_CARVE_MAX_UP,
                                                         mirror=self.config.gaussians.hair_carve_mirror)
            sd = surface_ray_depth(surface, cameras, hair, neck=self.config.gaussians.neck_cylinder if surface_mode == "replace" else "off")
            if self.config.gaussians.off_head_behind_ears and surface_mode == "replace":  # hair beside the face no nearer than the ears (model/surface.py)
                from .surface import off_head_behind_ears

                sd_near = sd
                sd = off_head_behind_ears(sd, surface, cameras)
            if self.config.gaussians.off_head_smooth > 0 and surface_mode == "replace":  # no steps in the off-head distances: no slits through long hair (model/surface.py)
                from .gaussian_head import foreground_weight
                from .surface import smooth_off_head_depth

                placed = (sd.t != sd_near.t) if self.config.gaussians.off_head_behind_ears else None  # behind the ears on purpose: kept
                gc = self.config.gaussians
                sd = smooth_off_head_depth(sd, foreground_weight(images.float()), gc.off_head_smooth, placed, gc.off_head_smooth_axis, gc.off_head_smooth_hold)
            if self.config.gaussians.off_head_hull != "off" and surface_mode == "replace":  # off-head pixels on the photos' visual hull (model/surface.py)
                from .gaussian_head import foreground_weight
                from .surface import off_head_on_hull

                sd = off_head_on_hull(sd, surface, cameras, foreground_weight(images.float()), self.config.gaussians.off_head_hull, OFF_HEAD_HULL_COLLAR,
                                      OFF_HEAD_HULL_DILATE_PX, free_tol_m=OFF_HEAD_HULL_FREE_TOL_M)
            if self.config.gaussians.stereo_depth_mm > 0 and surface_mode == "replace" and v > 1:  # the on-head pixels where the photos agree (model/stereo.py)
                sd = self._stereo_depth(images, cameras, sd)
            if self.config.gaussians.off_head_draw == "behind" and surface_mode == "replace":  # off-head pixels further back (model/surface.py off_head_draw_flags)
                from .gaussian_head import foreground_weight
                from .surface import off_head_draw_flags

                sd, _ = off_head_draw_flags(sd, cameras, foreground_weight(images.float()), "behind", behind_m=OFF_HEAD_BEHIND_M)
            if not isinstance(self.config.gaussians.flow_register, bool):
                raise ValueError(f"reconstruct: gaussians.flow_register must be true or false, got {self.config.gaussians.flow_register!r}")
            if self.config.gaussians.flow_register and surface_mode == "replace" and v > 1:  # the views' textures registered to each other (model/flowreg.py)
                images = self._flow_register(images, cameras, sd, surface, hair)
            ray_depth = sd.t[None]
            if surface_mode == "blend":
                from .surface import blend_network_depth

                ray_depth = lambda t_pred: blend_network_depth(sd, t_pred[0])[None]  # noqa: E731
            if self.config.expression_space == "ict53":
                if expressions is None:
                    expressions = torch.from_numpy(surface.expressions)
                if self.config.deform.prior:
                    head_fit = surface.head_fit(self.head_basis())
                    if self.config.gaussians.shell_on_hair and np.any(np.asarray(hair) > 0):  # the back-of-head shell under the hair the Gaussians lie on, not on the bald skull
                        shell_fit = surface.head_fit(self.head_basis(), hair)
        dev = self.device
        g = self.forward_gaussians(
            images.to(dev, torch.float32)[None], cameras.to(dev, torch.float32)[None], ray_depth if ray_depth is None or callable(ray_depth) else ray_depth.to(dev)
        )[0]
        v_real = v
        if surface is not None and surface_mode == "replace" and self.config.gaussians.mirror_views and self.config.expression_space == "ict53":
            # turned views' mirror images as virtual views of the unseen side, after the real ones (model/mirror.py); not in
            # blend mode: there the mirrored off-face pixels took a mirrored-only network pass's depth (a flap beside the neck)
            g, images, cameras, sd, expressions, v = self._add_mirrored_views(g, images, cameras, sd, expressions, surface)
        if surface is not None and surface_mode == "replace" and self.config.gaussians.photo_shapes != "off":  # colour / opacity / size from the photo (model/surface.py)
            from .surface import photo_pixel_shapes

            g = photo_pixel_shapes(g, images, self.config.gaussians.photo_shapes)
        view_index = torch.arange(v, device=dev).repeat_interleave(len(g) // v)  # Gaussians are V*S*S, view-major
        if surface is not None and surface_mode == "replace" and self.config.gaussians.grazing_stretch > 0:
            from .surface import stretch_to_patches, surface_steps  # grazing views' Gaussians cover their patch (model/surface.py)

            from .surface import behind_occluding_edges

            gc, c32 = self.config.gaussians, cameras.to(dev, torch.float32)
            near = behind_occluding_edges(sd.t.to(dev), c32, gc.grazing_edge_px) if gc.grazing_edge_px > 0 else None
            if gc.grazing_keep_features_mm > 0:  # not on the brows, eyes, nose and mouth (model/surface.py away_from_face_features)
                from .surface import away_from_face_features

                away = away_from_face_features(sd.t.to(dev), c32, surface, gc.grazing_keep_features_mm * 1e-3)
                near = away if near is None else near & away
            g = stretch_to_patches(g, *surface_steps(sd.t.to(dev), c32), gc.grazing_stretch, gc.grazing_min_ratio, where=near)
        margin = self.config.gaussians.edge_margin_px
        if margin > 0:  # matte-outline pixels are part wall: on profiles they would draw a streak down the face's midline
            from .gaussian_head import edge_source_index, edge_weight

            mode = self.config.gaussians.edge_mode
            if mode == "fade":
                g = g.replace(opacities=g.opacities * edge_weight(images.to(dev, torch.float32), margin).reshape(-1).to(g.opacities.dtype))
            elif mode == "colour":
                n = len(g) // v
                src = (edge_source_index(images, margin).reshape(v, -1).to(dev) + torch.arange(v, device=dev)[:, None] * n).reshape(-1)
                g = g.replace(colors=g.colors[src])
            else:
                raise ValueError(f"reconstruct: gaussians.edge_mode must be 'colour' or 'fade', got {mode!r}")
        off_sharp = None
        if surface is not None and surface_mode == "replace" and self.config.gaussians.off_head_draw not in ("off", "behind"):  # off-head Gaussians across another view's head (model/surface.py off_head_draw_flags)
            from .gaussian_head import foreground_weight
            from .surface import off_head_draw_flags

            sd, off_sharp = off_head_draw_flags(sd, cameras, foreground_weight(images.float()), self.config.gaussians.off_head_draw, v_real, tol_m=OFF_HEAD_COVER_TOL_M)
        if surface is not None:  # off the head next to the face is air: drop what a matte left there
            g = g.replace(opacities=g.opacities * (~sd.beyond_face).reshape(-1).to(dev, g.opacities.dtype))
        cover = self.config.gaussians.coverage_target
        if cover > 0 and (surface is not None or not self.config.gaussians.coverage_surface_only):
            from .coverage import fill_coverage  # each view's matte covered by the avatar (model/coverage.py)
            from .gaussian_head import foreground_weight

            c32, fg = cameras.to(dev, torch.float32), foreground_weight(images.to(dev, torch.float32))
            excl = None if surface is None else sd.beyond_face.to(dev)
            n_r = len(g) // v * v_real
            gr, _ = fill_coverage(g[:n_r], c32[:v_real], fg[:v_real], cover, None if excl is None else excl[:v_real])
            if v > v_real:  # mirrored views fill only what the real views leave uncovered; the real views' Gaussians are as without them
                excl = excl.clone()
                excl[:v_real] = True
                g, _ = fill_coverage(Gaussians.concat([gr, g[n_r:]]), c32, fg, cover, excl)
            else:
                g = gr
        thr = self.config.gaussians.prune_opacity
        dropped = None
        if v > v_real:  # optionally thin the mirrored views where a real one sees the head (model/mirror.py; off by default)
            from .mirror import thin_mirrored

            g, dropped = thin_mirrored(g, v_real, images, cameras, sd.t, self.config.gaussians, surface.head_to_world)
        n_ext = 0  # copies of long hair further back, appended after the pixel-aligned Gaussians (model/surface.py off_head_extrusion)
        if surface is not None and surface_mode == "replace" and self.config.gaussians.off_head_extrude_m > 0:
            g, view_index, n_ext = self._extrude_off_head(g, view_index, images, cameras, sd, surface, v_real)
        blend_data = None
        if v <= MAX_BLEND_VIEWS and (surface is not None or not self.config.gaussians.view_blend_surface_only):  # each view's depth, before pruning, for which views see each Gaussian (model/viewblend.py)
            from .gaussian_head import foreground_weight

            c32 = cameras.to(dev, torch.float32)
            fg = foreground_weight(images.to(dev, torch.float32))
            if dropped is not None:  # a mirrored view covers only where it kept its Gaussians (else real ones would fade into a hole)
                fg = fg * (~dropped).to(fg.dtype)
            n_px = len(g) - n_ext  # the pixel-aligned Gaussians
            depth = view_depth_maps(g.means[:n_px], c32, (g.opacities[:n_px] >= max(thr, 1e-6)) & (fg.reshape(-1) > 0.5))
            blend_data = (c32, fg, depth)
        if thr > 0:
            keep = g.opacities >= thr
            g, view_index = g[keep], view_index[keep]
        blend = under = None
        if blend_data is not None:
            c32, fg, depth = blend_data
            mask = coverage_masks(g.means, c32, fg, depth, view_index)
            sharp = None
            tol = self.config.gaussians.head_on_colour_tol
            if tol > 0 and surface is not None and v_real > 1:  # a view's Gaussians that a more head-on view sees in another colour blend sharply (model/viewblend.py)
                from .viewblend import contradicted_by_head_on_view

                sharp = contradicted_by_head_on_view(
                    g.means, g.colors, view_index, mask, c32, images.to(dev, torch.float32), surface.centre, views=v_real,
                    gain_deg=self.config.gaussians.head_on_gain_deg, colour_tol=tol,
                )  # fmt: skip
            if off_sharp is not None:  # off-head Gaussians drawn near their own camera only (off_head_draw)
                os_ = torch.cat([off_sharp.reshape(-1).to(dev), torch.ones(n_ext, dtype=torch.bool, device=dev)])  # the copies are off-head too
                os_ = os_[keep] if thr > 0 else os_
                if self.config.gaussians.off_head_draw == "headon_sharp" and v_real > 1:  # ... only where a covering real view sees their point more head-on
                    from .viewblend import contradicted_by_head_on_view

                    os_ = os_ & contradicted_by_head_on_view(g.means, g.colors, view_index, mask, c32, images.to(dev, torch.float32), surface.centre, views=v_real,
                                                             gain_deg=self.config.gaussians.head_on_gain_deg, colour_tol=-1.0)
                if self.config.gaussians.off_head_draw == "under":  # ... or drawn under the others in every frame instead
                    under = os_
                else:
                    sharp = os_ if sharp is None else sharp | os_
            if v > v_real and self.config.gaussians.mirror_under_below_chin:  # the mirrored views' neck and body drawn under the others (model/surface.py below_chin)
                from .surface import below_chin

                mb = (view_index >= v_real) & below_chin(g.means, surface, MIRROR_UNDER_CHIN_MARGIN_M)
                under = mb if under is None else under | mb
            offsets = None
            if v > v_real and self.config.gaussians.mirror_blend_offset_deg > 0:  # mirrored views count as further from every render camera
                offsets = torch.zeros(v, device=dev)
                offsets[v_real:] = float(self.config.gaussians.mirror_blend_offset_deg)
            vexpr = expressions.float().to(dev) if expressions is not None and self.config.deform.prior else None  # for the expression penalty (view_blend_expr_mm)
            blend = ViewBlend(view_index.to(torch.int8), mask, view_directions(c32), offsets, sharp, self.config.gaussians.head_on_tau_scale, under, vexpr)
        prior, n_int = None, 0
        if self.config.deform.prior:
            n_rec = len(g)
            anchor = self.config.deform.anchor_residual and blend is not None and blend.expressions is not None  # animate(): residual_anchor
            g, prior, n_int = self.build_prior(g, view_index if expressions is not None else None, expressions, head_fit=head_fit, shell_fit=shell_fit, anchor=anchor)
            if surface is not None and self.config.gaussians.shell_carve and self._shell_count() > 0 and n_int > 0:
                g = self._carve_shell(g, n_rec, images[:v_real], cameras[:v_real], surface)
        avatar = CanonicalAvatar(g, self.config.name, self.config.expression_space, prior, n_int, blend)
        self._deform_partial(avatar)
        return avatar

    def _extrude_off_head(self, g: Gaussians, view_index: Tensor, images: Tensor, cameras: Cameras, sd, surface, v_real: int):
        """``reconstruct``'s copies of long hair further back along the rays (``surface.off_head_extrusion``,
        ``gaussians.off_head_extrude_m``): each copy takes its pixel's Gaussian's colour, opacity,
        features and view, with isotropic scales of the larger of the Gaussian's largest scale and half
        the copies' spacing, and is appended after ``g`` (``V * S * S`` pixel-aligned Gaussians,
        view-major). Returns ``(gaussians, view_index, copies)``."""
        from .gaussian_head import foreground_weight
        from .surface import EXTRUDE_STEP_M, off_head_extrusion

        dev = self.device
        src, pts = off_head_extrusion(sd, surface, cameras, foreground_weight(images.float()), images, v_real, depth_m=self.config.gaussians.off_head_extrude_m)
        if len(src) == 0:
            return g, view_index, 0
        src = src.to(dev)
        r = torch.clamp(g.scales[src].max(-1).values, min=0.5 * EXTRUDE_STEP_M)
        quats = torch.zeros(len(src), 4, dtype=g.quats.dtype, device=dev)
        quats[:, 0] = 1.0
        copies = Gaussians(pts.to(dev, g.means.dtype), quats, r[:, None].expand(-1, 3).contiguous(), g.opacities[src], g.colors[src],
                           None if g.features is None else g.features[src])
        log.info("reconstruct: %d copies of long hair further back (off_head_extrude_m)", len(src))
        return Gaussians.concat([g, copies]), torch.cat([view_index, view_index[src]]), len(src)

    def _stereo_depth(self, images: Tensor, cameras: Cameras, sd):
        """``reconstruct``'s surface depth ``sd`` with its hit pixels moved along their rays, within
        ``gaussians.stereo_depth_mm`` of the surface, to where the input photos agree
        (``model/stereo.py``); the other pixels and masks unchanged."""
        import dataclasses

        from .gaussian_head import foreground_weight
        from .stereo import StereoConfig, stereo_ray_depth

        r = self.config.gaussians.stereo_depth_mm * 1e-3
        cfg = StereoConfig(range_m=r, step_m=min(StereoConfig.step_m, r))
        st = stereo_ray_depth(images.float().cpu(), cameras.to("cpu", torch.float32), sd.t, sd.hit, foreground_weight(images.float().cpu()), cfg)
        return dataclasses.replace(sd, t=st.t.to(sd.t))

    def _flow_register(self, images: Tensor, cameras: Cameras, sd, surface, hair) -> Tensor:
        """``reconstruct``'s inputs with each view's texture registered to its neighbour's by optical
        flow through the tracked surface (``model/flowreg.py``, ``gaussians.flow_register``), clipped to
        ``gaussians.flow_register_clip_px``. Raises ``ValueError`` on a clip that is not a finite number > 0."""
        from .flowreg import register_views

        clip = self.config.gaussians.flow_register_clip_px
        if isinstance(clip, bool) or not isinstance(clip, (int, float)) or not np.isfinite(clip) or clip <= 0:
            raise ValueError(f"reconstruct: gaussians.flow_register_clip_px must be a finite number > 0, got {clip!r}")
        reg = register_views(images.float().cpu(), cameras, sd, surface, hair, clip_px=float(clip), sigma_px=FLOW_REGISTER_SIGMA_PX, falloff_px=FLOW_REGISTER_FALLOFF_PX,
                             where=sd.face_hit if FLOW_REGISTER_FACE_ONLY else None, mode=FLOW_REGISTER_MODE)
        log.info("reconstruct: flow registration of views %s to %s", list(range(len(reg.parent))), reg.parent)
        return reg.images.to(images)

    def _shell_count(self) -> int:
        """How many ungated shell Gaussians ``_prior_extras`` appends after the reconstructed ones: the
        back-of-head shell's (``deform.back_shell``), the chin shell's (``deform.chin_shell``), the
        cheek shell's (``deform.cheek_shell``) and then the face shell's (``deform.face_shell``)."""
        from .prior import back_shell_vertices, cheek_shell_vertices, chin_shell_vertices, face_shell_vertices

        basis = self.head_basis()
        d = self.config.deform
        return (len(back_shell_vertices(basis)) * bool(d.back_shell) + len(chin_shell_vertices(basis)) * bool(d.chin_shell)
                + len(cheek_shell_vertices(basis)) * bool(d.cheek_shell) + len(face_shell_vertices(basis, d.face_shell)))

    def _carve_shell(self, g: Gaussians, n_rec: int, images: Tensor, cameras: Cameras, surface) -> Gaussians:
        """``reconstruct``'s back-of-head and chin shells (the ``_shell_count()`` Gaussians after the
        ``n_rec`` reconstructed ones) moved towards the head centre until every real input's matte
        holds it (``surface.carve_into_mattes``): the fitted head can be wider than the person's, and an
        opaque shell beyond a photo's outline is drawn as a dark rim beside the hair. The crops' padding
        beyond their photos' edges (``surface.frames``) holds every point: a photo whose frame cuts the
        hair does not cut the shell."""
        from .gaussian_head import foreground_weight
        from .surface import carve_into_mattes, midline_reflection

        k = self._shell_count()
        if k == 0 or len(g) < n_rec + k:
            return g
        means = g.means.clone()
        fg = foreground_weight(images.float())
        fg = torch.maximum(fg, surface.padding(fg.shape[-1], fg.shape[-2]).to(fg))  # the crops' padding holds every point (HeadSurface.frames)
        mirror = midline_reflection(surface.head_to_world) if self.config.gaussians.hair_carve_mirror else None
        means[n_rec : n_rec + k] = carve_into_mattes(means[n_rec : n_rec + k].float().cpu(), cameras.to("cpu", torch.float32), fg.cpu(), surface.centre,
                                                     dilate_px=SHELL_CARVE_DILATE_PX, mirror=mirror).to(means)
        return g.replace(means=means)

    def _add_mirrored_views(self, g: Gaussians, images: Tensor, cameras: Cameras, sd, expressions: Tensor | None, surface):
        """``reconstruct``'s mirrored virtual views (``model/mirror.py``): the real views' Gaussians
        ``g`` (``V*S*S``) followed by those of the mirrors of the views turned by at least
        ``gaussians.mirror_min_yaw_deg`` (a second network pass over the mirrored views alone), so
        that at most ``MAX_BLEND_VIEWS`` views result. Returns ``(gaussians, images, cameras,
        surface depth, expressions, views)`` of all views, real first (unchanged when none is turned)."""
        from .mirror import mirrored_views

        v = images.shape[0]
        gc = self.config.gaussians
        mv = mirrored_views(images, cameras, sd, expressions, gc.mirror_min_yaw_deg, surface.head_to_world, limit=MAX_BLEND_VIEWS - v)
        if mv is None:
            return g, images, cameras, sd, expressions, v
        from .surface import SurfaceDepth

        dev, m = self.device, len(mv)
        msd = mv.depth  # every mirrored pixel on the mirrored head (replace mode only)
        gm = self.forward_gaussians(mv.images.to(dev, torch.float32)[None], mv.cameras.to(dev, torch.float32)[None], msd.t[None].to(dev))[0]
        log.info("reconstruct: %d mirrored view(s) of input view(s) %s", m, mv.source)
        cat = lambda a, b: None if a is None or b is None else torch.cat([a, b.to(a)])  # noqa: E731
        sd = SurfaceDepth(cat(sd.t, msd.t), cat(sd.hit, msd.hit), cat(sd.beyond_face, msd.beyond_face), cat(sd.face_hit, msd.face_hit))
        if expressions is not None:
            expressions = torch.cat([expressions, mv.expressions.to(expressions)])
        images = torch.cat([images, mv.images.to(images)])
        cameras = Cameras.stack([cameras, mv.cameras.to(cameras.K.device, cameras.K.dtype)])
        return Gaussians.concat([g, gm]), images, cameras, sd, expressions, v + m

    # ------------------------------------------------------------ animation
    def _deform_partial(self, avatar: CanonicalAvatar) -> Tensor:
        """The avatar's cached first-layer partial ``[N, H]``, computed on first use for this model."""
        g = avatar.gaussians[: avatar.num_reconstructed]  # the mouth interior has no MLP residual
        cache = avatar.deform_cache
        if (
            cache is None
            or avatar.deform_cache_owner != id(self.deform)
            or avatar.deform_cache_source is not avatar.gaussians  # Gaussians replaced since (same count or not)
            or cache.shape != (len(g), self.config.deform.hidden_size)
            or cache.device != self.device
        ):
            with torch.no_grad():
                cache = self.deform.precompute(g.features.to(self.device), g.means.to(self.device))
            avatar.deform_cache, avatar.deform_cache_owner, avatar.deform_cache_source = cache, id(self.deform), avatar.gaussians
        return cache

    def _offsets_at_views(self, view_index: Tensor, view_expressions: Tensor, offset) -> Tensor:
        """``[N, 3]`` float32 on the model's device: ``offset(sel, z)`` (the deformation MLP's ``dxyz`` of
        the Gaussians ``sel`` at the expression ``z [E]``) for each Gaussian at its own view's expression
        (``view_index [N]`` into ``view_expressions [V, E]``; 0 for a Gaussian without a view, index -1).
        One MLP pass per view; no autograd. Used by the prior's binding (``build_prior(anchor=True)``)
        and by ``residual_anchor``, so both draw the anchor the same way."""
        dev = self.device
        vi = view_index.to(dev).long()
        ve = view_expressions.to(dev, torch.float32)
        out = torch.zeros(len(vi), 3, device=dev)
        with torch.no_grad():
            for v in range(int(ve.shape[0])):
                sel = (vi == v).nonzero().squeeze(1)
                if len(sel):
                    out[sel] = offset(sel, ve[v]).float()
        return out

    def residual_anchor(self, avatar: CanonicalAvatar) -> Tensor | None:
        """``[N_reconstructed, 3]`` float32 on the model's device, or None: what ``animate`` subtracts from
        the deformation MLP's residual of each reconstructed Gaussian, its residual at its own input
        view's expression ``MLP(f, x, z_view)`` (``deform.anchor_residual``; avatars whose per-view
        data holds the views' expressions, ``ViewBlend.expressions``: those reconstructed on a tracked
        head surface). At its photo's expression each Gaussian then lies where reconstruction put it.

        Why: the MLP was trained on the network's depth, where its expression-independent part (2-4 mm
        median) corrects that depth; on the tracked surface the Gaussians already lie on their pixels'
        rays, and that part moved them off (about 1 cm at the nose), opening the gaps beside the nose
        through which the back-of-head shell showed as a dark blot (docs/model-card-log.md). Cached on the
        avatar with the MLP's first-layer term (``_deform_partial``). View expressions of another shape
        than ``[V, E]`` (a malformed file, which loads: ``view.expr``) give None, with a warning."""
        vb = avatar.view_blend
        if not self.config.deform.anchor_residual or vb is None or vb.expressions is None:
            return None
        if tuple(vb.expressions.shape) != (vb.directions.shape[0], self.config.expression_dim):  # a file's malformed view.expr
            if not avatar.__dict__.get("_residual_anchor_warned"):
                log.warning("avatar's view expressions have shape %s, not [%d, %d]: drawn without residual_anchor",
                            list(vb.expressions.shape), vb.directions.shape[0], self.config.expression_dim)  # fmt: skip
                avatar.__dict__["_residual_anchor_warned"] = True
            return None
        partial = self._deform_partial(avatar)
        hit = avatar.__dict__.get("_residual_anchor")
        if hit is not None and hit[0] is partial and hit[1] is vb:
            return hit[2]
        anchor = self._offsets_at_views(vb.source_view, vb.expressions, lambda sel, z: self.deform.forward_split(partial[sel], z)[0])
        avatar.__dict__["_residual_anchor"] = (partial, vb, anchor)
        return anchor

    def serving_nbytes(self, avatar: CanonicalAvatar) -> int:
        """Bytes ``avatar`` holds once this model has animated it: its Gaussians, its prior binding, the
        deformation MLP's cached first layer (``[N_reconstructed, H]`` float32; with ``residual_anchor``
        also ``[N_reconstructed, 3]``) and the binding's
        per-frame runtime on this model's device (``PriorRuntime.estimate_nbytes``), and the view-blending
        data (``ViewBlend.nbytes``; with ``gaussians.view_blend_expr_mm > 0`` before the first frame the
        expression penalty's tables at most, ``ExpressionPenalty.estimate_nbytes``). What
        the server's avatar budget counts; an avatar without a binding counts none (it gets one on its
        first frame). Computed from the sizes, without building the caches.
        """
        n = len(avatar.gaussians)
        total = int(avatar.nbytes) + avatar.num_reconstructed * int(self.config.deform.hidden_size) * 4
        if avatar.view_blend is not None:  # per-view data and its per-frame pair index (model/viewblend.py)
            vb = avatar.view_blend
            total += vb.nbytes
            if self.config.gaussians.view_blend_expr_mm > 0 and vb.expressions is not None and "_expr" not in vb.__dict__:
                from .viewblend import ExpressionPenalty  # its tables, built on the first frame: at most this

                total += ExpressionPenalty.estimate_nbytes(len(vb), vb.directions.shape[0])
            if self.config.deform.anchor_residual and vb.expressions is not None:  # residual_anchor: [N_reconstructed, 3] float32
                total += avatar.num_reconstructed * 3 * 4
        if avatar.prior is not None:
            total += sum(t.numel() * t.element_size() for t in vars(avatar.prior).values() if isinstance(t, Tensor))
            if self.config.deform.prior and len(avatar.prior) == n:
                from .prior import PriorRuntime

                total += PriorRuntime.estimate_nbytes(avatar.prior, self.head_basis(), self.device.type, rotate=self.config.deform.prior_rotate)
        return total

    def compile_deformation(self, bf16: bool = False, cuda_graphs: bool = False) -> float:
        """``torch.compile`` the per-frame deformation layers and compile them now, with one dummy call in
        the mode ``animate(bf16=bf16)`` uses. Returns the seconds it took; on failure (no C++ compiler
        for inductor, ...) the MLP stays eager and the error is raised.

        ``cuda_graphs``: compile with ``mode="reduce-overhead"`` (CUDA graphs; a CUDA device only)."""
        if cuda_graphs and self.device.type != "cuda":
            raise ValueError(f"CUDA graphs need a CUDA device, the model is on {self.device}")
        t0 = time.perf_counter()
        self.deform.compile_tail(True, mode="reduce-overhead" if cuda_graphs else None)
        try:
            partial = torch.zeros(8192, self.config.deform.hidden_size, device=self.device)  # one full chunk
            z = torch.zeros(self.config.expression_dim, device=self.device)
            ctx = torch.autocast(device_type=self.device.type, dtype=torch.bfloat16) if bf16 else nullcontext()
            with torch.inference_mode(), ctx:
                for _ in range(3 if cuda_graphs else 1):  # CUDA graphs record on a later call than the first
                    self.deform.forward_split(partial, z)
        except Exception:
            self.deform.compile_tail(False)
            raise
        return time.perf_counter() - t0

    @torch.inference_mode()  # one grad mode for every caller: a compiled MLP then never recompiles
    def animate(
        self, avatar: CanonicalAvatar, expression: Any, bf16: bool = False, prior: bool = True, camera: Cameras | None = None
    ) -> Gaussians | list[Gaussians]:
        """Deform the avatar to ``expression [E]`` (-> ``Gaussians``) or ``[B, E]`` (-> ``list[Gaussians]``).

        Uses the split first layer (cached on the avatar). ``bf16=True`` runs the per-frame layers under
        CPU/CUDA bf16 autocast (outputs are float32). With the expression prior (``config.deform.prior``)
        the avatar's head-surface displacement is added to the MLP's residual (an avatar without a
        binding gets one first, see ``attach_prior``); ``prior=False`` leaves it out (an ablation).
        Trailing mouth-interior / eyelid Gaussians that the expression keeps hidden are left out of
        the result, so it may hold fewer Gaussians than the avatar (never fewer than
        ``avatar.num_reconstructed``). One expression on the CPU in float32 (the server's frame) takes
        ``PriorRuntime.frame``: the same Gaussians in one numba pass, leaving out trailing gated runs
        whose opacity is below the rasterizer's ``ALPHA_MIN`` (the image is the same).

        ``camera`` (batch ``[1]``, the frame's render camera, optional): with
        ``config.gaussians.view_blend_tau_deg > 0`` and an avatar with per-view data
        (``avatar.view_blend``), each reconstructed Gaussian's opacity is multiplied by its source
        view's weight for that camera (``model/viewblend.py``); otherwise the camera is ignored.
        """
        if avatar.expression_space != self.config.expression_space:
            raise ValueError(
                f"avatar uses expression space {avatar.expression_space!r} but model {self.config.name!r} "
                f"uses {self.config.expression_space!r}"
            )
        if avatar.gaussians.num_features != self.config.gaussians.feature_dim:
            raise ValueError(
                f"avatar has {avatar.gaussians.num_features} features per Gaussian, model expects {self.config.gaussians.feature_dim}"
            )
        dev = self.device
        z = torch.as_tensor(expression, dtype=torch.float32).to(dev)
        e = self.config.expression_dim
        if z.ndim not in (1, 2) or z.shape[-1] != e:
            raise ValueError(f"expression must have shape [{e}] or [B, {e}] for space {self.config.expression_space!r}, got {list(z.shape)}")
        if self.config.deform.prior and avatar.prior is None:
            with torch.inference_mode(False):
                self.attach_prior(avatar)
        partial = self._deform_partial(avatar)
        ctx = torch.autocast(device_type=dev.type, dtype=torch.bfloat16) if bf16 else nullcontext()
        with ctx:
            dxyz, drgb = self.deform.forward_split(partial, z)
        dxyz, drgb = dxyz.float(), drgb.float()
        anchor = self.residual_anchor(avatar)
        if anchor is not None:  # the residual relative to each Gaussian's own view's expression (deform.anchor_residual)
            dxyz = dxyz - anchor
        g = avatar.gaussians if avatar.gaussians.means.device == dev else avatar.gaussians.to(dev)
        n_int = avatar.num_interior
        prior_d = gate = shade = rot = None
        if self.config.deform.prior and avatar.prior is not None:
            rt = avatar.prior_runtime
            if (
                rt is None
                or rt.source is not avatar.prior  # another binding (same size or not)
                or rt.n != len(g)
                or rt.basis_u.device != dev
                or rt.shading_on != bool(self.config.deform.prior_shading)
                or rt.rotate_on != bool(self.config.deform.prior_rotate)
                or (rt.shading_on and rt.light_of is not avatar.gaussians.colors)  # recoloured: the light is re-estimated
            ):
                with torch.inference_mode(False):
                    rt = avatar.prior_runtime = self._runtime(avatar.prior.to(dev), g, n_int)
                rt.source = avatar.prior  # what this per-avatar cache was built from
                rt.light_of = avatar.gaussians.colors
            if prior and z.ndim == 1 and dev.type == "cpu" and g.means.dtype == torch.float32:
                return self.blend_views(avatar, rt.frame(g, n_int, dxyz, drgb, z), camera, z)  # one numba pass, the same Gaussians as below
            if prior:
                prior_d = rt.displacement(z)  # [N, 3] or [B, N, 3]
                shade = rt.shading(z) if rt.shading_on else None  # [N] or [B, N]
                rot = rt.rotation(z) if rt.rotate_on else None  # [N, 4] or [B, N, 4]
            gate = self._gate(z, rt)
        if z.ndim == 1:
            return self.blend_views(avatar, _combine(g, dxyz, drgb, prior_d, n_int, gate, trim=True, shade=shade, rot=rot), camera, z)
        return [
            self.blend_views(
                avatar,
                _combine(g, dxyz[i], drgb[i], None if prior_d is None else prior_d[i], n_int, None if gate is None else gate[i], trim=True, shade=None if shade is None else shade[i], rot=None if rot is None else rot[i]),
                camera,
                z[i],
            )
            for i in range(z.shape[0])
        ]

    def blend_views(self, avatar: CanonicalAvatar, g: Gaussians, camera: Cameras | None, expression: Tensor | None = None) -> Gaussians:
        """``g`` (a frame of ``avatar``, as ``animate`` returns it without a camera) with its first
        ``avatar.num_reconstructed`` Gaussians' opacities multiplied by their source view's weight for
        ``camera`` (batch ``[1]``; ``model/viewblend.py``). ``animate(avatar, z, camera=c)`` is
        ``blend_views(avatar, animate(avatar, z), c, z)``; callers that render one frame from several
        cameras deform once and weight per camera, passing the frame's expression. With that
        ``expression [E]``, ``gaussians.view_blend_expr_mm > 0``, an avatar whose per-view data holds
        its input views' expressions and a prior binding whose runtime ``animate`` has built (without
        one: the angle alone), the weights take the expression penalty too
        (``ViewBlend.factors``: the views whose expression is nearest the frame's there win).
        Returns ``g`` itself when ``gaussians.view_blend_tau_deg`` is 0, ``camera`` is None or the
        avatar has no per-view data."""
        tau = float(self.config.gaussians.view_blend_tau_deg)
        vb = avatar.view_blend
        if camera is None or tau <= 0 or vb is None:
            return g
        n = avatar.num_reconstructed
        if len(vb) != n or len(g) < n:
            return g
        sigma = float(self.config.gaussians.view_blend_expr_mm)
        rt = avatar.prior_runtime if expression is not None and sigma > 0 and vb.expressions is not None and avatar.prior is not None else None
        if rt is not None and (getattr(rt, "source", None) is not avatar.prior or rt.n != len(avatar.gaussians)):
            rt = None  # not this avatar's binding: angle factors alone
        f = vb.to(g.opacities.device).factors(camera, tau, expression, sigma, rt, avatar.gaussians.means[:n] if rt is not None else None).to(g.opacities.dtype)
        op = g.opacities.clone()
        op[:n] = op[:n] * f
        if vb.under is not None:  # off-head Gaussians drawn under the others for this camera (model/viewblend.py push_under)
            from .viewblend import push_under

            sel = torch.zeros(len(g), dtype=torch.bool, device=g.means.device)
            sel[:n] = vb.under.to(g.means.device)
            means, scales = push_under(g.means, g.scales, camera, sel)
            return g.replace(opacities=op, means=means, scales=scales)
        return g.replace(opacities=op)


def load_model(
    name_or_dir: str | Path = "tiny",
    device: Any = "cpu",
    dino_weights: str | Path | None = None,
    vae_weights: str | Path | None = None,
) -> FastGHA:
    """Load a model in eval mode.

    Args:
        name_or_dir: a preset name (``"tiny"``, ``"paper"``) -- its shipped weights from
            ``fastgha_core/assets/models/<name>/`` when present, else a randomly initialised model
            (with a warning) -- or a folder written by ``save_pretrained``.
        device: torch device.
        dino_weights / vae_weights: optional local pretrained encoder folders (then frozen).
    """
    name = str(name_or_dir)
    if name in PRESETS:
        folder = ASSET_MODELS_DIR / name
        if (folder / CONFIG_NAME).is_file() and (folder / WEIGHTS_NAME).is_file():
            model = FastGHA.from_pretrained(folder)
        else:
            log.warning("no shipped weights for model %r in %s: using a randomly initialised model", name, folder)
            model = FastGHA(get_preset(name))
    elif Path(name).is_dir():
        model = FastGHA.from_pretrained(name)
    else:
        raise ValueError(f"unknown model {name!r}: expected a preset name {sorted(PRESETS)} or a folder written by save_pretrained")
    if dino_weights is not None or vae_weights is not None:
        model.load_pretrained_encoders(dino_weights, vae_weights)
    return model.to(device).eval()
