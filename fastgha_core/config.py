"""Model configuration: one dataclass per stage, nested in ``FastGHAConfig``, plus named presets.

``PRESETS["paper"]`` follows the paper's appendix table (dinov3-vitl16, SD-Turbo VAE, transformer
512 x 8, decoder 512 in / 44 out, deformation MLP 256 x 6). ``PRESETS["tiny"]`` is the same set of
classes at CPU size (128^2 in and out, encoders trained from scratch). A config serialises to plain
JSON (``to_dict``/``from_dict``), which is what ``FastGHA.save_pretrained`` writes as ``config.json``.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "DinoConfig",
    "VAEConfig",
    "TransformerConfig",
    "DecoderConfig",
    "GaussianHeadConfig",
    "DeformConfig",
    "FastGHAConfig",
    "PRESETS",
    "get_preset",
    "check_field_types",
]


@dataclass
class DinoConfig:
    """Semantic encoder: a ``transformers`` DINOv3 ViT plus the convs that fuse its layers."""

    hidden_size: int = 1024  # ViT width (dinov3-vitl16: 1024)
    num_layers: int = 24  # transformer blocks (dinov3-vitl16: 24)
    num_heads: int = 16  # attention heads (head dim must be divisible by 4 for DINOv3's 2D RoPE)
    intermediate_size: int = 4096  # MLP width inside each block
    patch_size: int = 16  # pixels per patch side; patch tokens lie on an H/p x W/p grid
    num_register_tokens: int = 4  # register tokens after CLS (dropped with CLS before fusion)
    layerscale_value: float = 1.0  # initial LayerScale value (pretrained weights overwrite it)
    use_gated_mlp: bool = False  # SwiGLU MLP (the ViT-7B/H+ variants) instead of GELU MLP
    rope_theta: float = 100.0  # RoPE base period
    pos_embed_rescale: float | None = None  # RoPE coordinate jitter in train mode (DINOv3 uses 2.0); None = deterministic
    feature_layers: tuple[int, ...] = (6, 12, 18, 24)  # 1-based blocks whose patch tokens are fused
    out_channels: int = 256  # channels of the fused map F_dino at H/8 (paper: 256)
    frozen: bool = True  # no gradients, eval mode (set when pretrained weights are loaded)

    def to_hf(self):
        """The equivalent ``transformers.DINOv3ViTConfig``."""
        from transformers import DINOv3ViTConfig

        kw: dict[str, Any] = dict(
            hidden_size=self.hidden_size,
            num_hidden_layers=self.num_layers,
            num_attention_heads=self.num_heads,
            intermediate_size=self.intermediate_size,
            patch_size=self.patch_size,
            num_register_tokens=self.num_register_tokens,
            layerscale_value=self.layerscale_value,
            use_gated_mlp=self.use_gated_mlp,
            rope_theta=self.rope_theta,
        )
        cfg = DINOv3ViTConfig(**kw)
        cfg.pos_embed_rescale = self.pos_embed_rescale
        return cfg


@dataclass
class VAEConfig:
    """Colour encoder: the ``diffusers`` AutoencoderKL encoder (+ quant conv); we keep the latent mean."""

    block_out_channels: tuple[int, ...] = (128, 256, 512, 512)  # SD VAE; len-1 downsamplings (4 -> H/8)
    layers_per_block: int = 2  # resnets per down block
    latent_channels: int = 4  # C_e, channels of F_enc
    norm_num_groups: int = 32  # GroupNorm groups (must divide every block width)
    scaling_factor: float = 0.18215  # latents are multiplied by this (SD convention: ~unit variance)
    frozen: bool = True  # no gradients, eval mode (set when pretrained weights are loaded)


@dataclass
class TransformerConfig:
    """Multi-view transformer: pre-norm self-attention over all V*(H/8)*(W/8) tokens jointly."""

    hidden_size: int = 512  # token width (paper: 512)
    num_layers: int = 8  # self-attention blocks (paper: 8)
    num_heads: int = 8  # attention heads
    mlp_ratio: float = 4.0  # MLP width = mlp_ratio * hidden_size


@dataclass
class DecoderConfig:
    """The SD VAE decoder with conv_in widened to the token width, cross-view mid attention and
    conv_out widened to the Gaussian channels."""

    block_out_channels: tuple[int, ...] = (128, 256, 512, 512)  # SD VAE decoder widths (reversed inside)
    layers_per_block: int = 2  # the up blocks hold layers_per_block + 1 resnets each
    norm_num_groups: int = 32  # GroupNorm groups
    cross_view_attention: bool = True  # mid-block attention over the tokens of all views jointly
    init_from_vae: bool = True  # copy the pretrained VAE decoder weights where shapes allow (with vae_weights)


@dataclass
class GaussianHeadConfig:
    """Activations of the raw Gaussian maps (see ``model/gaussian_head.py``)."""

    feature_dim: int = 32  # per-Gaussian feature f (paper: 32); maps have 12 + feature_dim channels
    depth_range: float = 0.35  # metres; depth along a ray = |camera centre| + depth_range * tanh(raw)
    min_scale_px: float = 0.25  # smallest scale, in pixel footprints at the Gaussian's depth
    max_scale_px: float = 16.0  # largest scale, in pixel footprints at the Gaussian's depth
    prune_opacity: float = 0.005  # reconstruct() drops Gaussians less opaque than this (0 = keep all)
    depth_parity_sigma: float = 0.0  # > 0: take the row-alternating (Nyquist in y) part out of each view's predicted depth, its amplitude averaged over this many pixels (model/gaussian_head.py remove_row_parity; 0 = off; docs/model-card-log.md "The row-alternating depth")
    rgb_residual: bool = False  # colour = sigmoid(raw + logit(input pixel)): predict a residual on the pixel's own colour
    foreground_opacity: bool = False  # opacity *= foreground of the (matted) input pixel: background pixels make no Gaussians
    edge_margin_px: float = 3.0  # reconstruct(): Gaussians of input pixels within this many pixels of their view's background are treated by edge_mode (0 = off; model/gaussian_head.py edge_weight)
    edge_mode: str = "colour"  # what edge_margin_px does to outline Gaussians: "colour" (take the nearest interior pixel's colour) or "fade" (opacity)
    coverage_target: float = 0.9  # reconstruct(): raise the opacity of each view's own Gaussians where the avatar covers its matte less than this (0 = off; model/coverage.py)
    hair_fit: bool = True  # reconstruct() on a tracked head surface ("replace"): push the bald head's scalp out by a hair thickness fitted to the inputs' mattes (model/surface.py fit_hair_thickness)
    hair_carve: bool = True  # ... and thin it per vertex where it would stand out beyond an input's matte (model/surface.py hair_carve_fractions)
    hair_carve_mirror: bool = True  # ... and carve the hair and the back-of-head shell also where their mirror image (about the head's midline) stands beyond a matte: the back of a head only one side photo sees (model/surface.py hair_carve_fractions, carve_into_mattes; on since 2026-12-03: phone-5's side views draw 19 / 18 % beyond their outline instead of 28 / 30 %, leave-one-out PSNR within 0.03 dB per set and identity 0.448 -> 0.446, studio-4's +55 view -0.15 dB; docs/model-card-log.md "Beyond the photo's outline")
    shell_on_hair: bool = True  # ... and lay the back-of-head shell (model/prior.py back_shell) on the scalp laid out by that thickness, not on the bald skull under the hair's Gaussians (model/surface.py HeadSurface.head_fit)
    neck_cylinder: str = "off"  # reconstruct() on a tracked head surface ("replace"): "off_head": off-head pixels whose ray enters the tracked neck continued as a cylinder along the head's up axis, below the chin, lie there instead of at the nearest head pixel's distance; "below_ring": so do the mesh's own pixels below its neck ring; "off" (default: both lowered the real-photo means, docs/model-card-log.md; model/surface.py neck_cylinder_depth)
    off_head_extrude_m: float = 0.10  # reconstruct() on a tracked head surface ("replace"): hair-coloured off-head pixels beside the head (long hair a frontal photo sees only as a strip beside the face) also get copies further back along their rays, 6 mm apart, up to this many metres behind the ears' plane, while every real input's matte holds each copy and its mirror image and it stays within 5 cm of the fitted head; drawn under the other Gaussians (0 = off; model/surface.py off_head_extrusion; docs/model-card-log.md "Long hair behind the ears")
    off_head_behind_ears: bool = True  # reconstruct() on a tracked head surface ("replace"): off-head pixels beside the face (more than 6 cm from the midline, between the chin and the brows, in front of the ears, seen by a view within 45 degrees of the front) are pushed back along their rays to the ears' plane, by up to 15 cm, instead of lying at the cheek outline's distance (model/surface.py off_head_behind_ears; docs/model-card-log.md "Hair beside the face")
    off_head_smooth: float = 0.11  # reconstruct() on a tracked head surface ("replace"): relax the off-head pixels' nearest-hit distances (a piecewise-constant field whose steps open slits of background through long hair in other views) towards a membrane between the head's, over about this fraction of the input's side (0.11: ~14 pixels at 128²; 0 = off); pixels off_head_behind_ears placed keep their distance (model/surface.py smooth_off_head_depth; docs/model-card-log.md "Slits through long hair")
    off_head_smooth_hold: float = 0.05  # ... except within this fraction of the input's side of the head's outline (6 pixels at 128²), where the nearest head pixel's distance stays: relaxed there, studio-4's +55 view lost the hair behind the ear (-0.73 dB) and dlib read the open jaw 0.03 shorter
    off_head_smooth_axis: str = "vertical"  # ... along image columns only ("vertical", the way long hair hangs: relaxed both ways, a turned head's torso tilted into a sheet that drew stripes beside the neck) or "both"
    off_head_hull: str = "off"  # reconstruct() on a tracked head surface ("replace"): off-head pixels of each input's matte are moved onto the visual hull of the other inputs' mattes instead of lying at the nearest head pixel's distance: "entry" (where the ray enters it), "nearest" (kept where the hull holds them, else the nearest hull point), "middle" (halfway through it); "off" (default: no mode raised the real-photo leave-one-out means, docs/model-card-log.md; model/surface.py off_head_on_hull)
    off_head_draw: str = "under"  # reconstruct() on a tracked head surface ("replace"): where/when the off-head pixels' Gaussians are drawn: "behind" (pushed OFF_HEAD_BEHIND_M further along their ray), "drop" (dropped where they lie in front of another real view's head), "sharp" (all drawn near their own camera only), "headon_sharp" (those a covering real view sees >= head_on_gain_deg more head-on drawn near their own camera only), "cover_sharp" (those in front of another view's head drawn near their own camera only), "under" (all drawn under the other Gaussians in every frame: only where the head leaves the frame uncovered; model/viewblend.py push_under; the default: +0.05 dB mean real-photo leave-one-out PSNR, higher on all three sets, docs/model-card-log.md); "off" (no change; model/surface.py off_head_draw_flags)
    shell_carve: bool = True  # reconstruct() on a tracked head surface: move each back-of-head shell Gaussian towards the head centre until every input's matte holds it (model/surface.py carve_into_mattes)
    head_on_colour_tol: float = 0.25  # reconstruct() on a tracked head surface: a real view's Gaussians whose colour differs by more than this (any channel, 0..1) from what the view that sees their point most head-on shows there are drawn by their own camera's angle alone, exp(-angle / (view_blend_tau_deg x head_on_tau_scale)) (0 = off; model/viewblend.py contradicted_by_head_on_view, ViewBlend.sharp; docs/model-card-log.md)
    head_on_gain_deg: float = 15.0  # ... only when that view sees the point at least this many degrees more squarely than the Gaussian's own view
    head_on_tau_scale: float = 0.25  # ... their fall-off, as a fraction of view_blend_tau_deg (0.25: 5 degrees)
    coverage_surface_only: bool = True  # apply coverage_target only when reconstructing on a tracked head surface (model/surface.py)
    grazing_stretch: float = 0.5  # reconstruct() on a tracked head surface: lengthen each pixel's Gaussian along the surface by this x its patch's excess length where the view sees the surface at a grazing angle (a standard deviation per metre of patch: 0.5 spans the patch; 0 = off; on since 2026-12-03: closes the gaps between a frontal photo's pixel columns that side views showed as stripes across the cheek, real-photo leave-one-out PSNR +0.24 dB on studio-4, the other sets within 0.02, identity +0.003 on average, within the spread of the variants measured; 1.0: +0.43 dB on studio-4 but hair smeared down the temple of phone-5's -70 render; docs/model-card-log.md "The cheek stripes of side views"; model/surface.py stretch_to_patches)
    stereo_depth_mm: float = 0.0  # reconstruct() on a tracked head surface ("replace"): move each real view's on-head pixel along its ray, within +- this many millimetres of the surface, to where the other input photos agree with it (band-passed NCC plane sweep; 0 = off, the default: docs/model-card-log.md "Photo-consistency depth of the on-head pixels"; model/stereo.py)
    grazing_edge_px: int = 0  # ... only within this many pixels behind an occluding edge of the surface (the far side of the nose ridge; 0 = everywhere, the default since 2026-12-03; model/surface.py behind_occluding_edges)
    grazing_keep_features_mm: float = 25.0  # ... never within this many millimetres of the tracked head's brow, nose, eye and mouth landmarks (0 = there too: stretched there it blurred the eye corners and smeared the nose tip forward in profiles; model/surface.py away_from_face_features)
    grazing_min_ratio: float = 2.5  # ... only Gaussians whose patch of surface is longer than this many pixel footprints (incidence beyond ~66 deg; model/surface.py stretch_to_patches min_ratio)
    view_blend_tau_deg: float = 20.0  # frames: each input view's Gaussians' opacity x exp(-(angle of its camera to the render camera - smallest such angle among the views that see the Gaussian's point) / tau), degrees (0 = off; 20 from real-photo leave-one-out, docs/model-card-log.md; model/viewblend.py; avatars without view data render unweighted)
    view_blend_expr_mm: float = 0.0  # frames with view blending: also penalise each input view by how far its tracked expression puts the Gaussian's bound surface point from where the frame's expression puts it, |D_g (e_frame - e_view)| in mm / this, in one combined penalty with the angle (0 = off, the default: 8 mm measured, real-photo leave-one-out +0.01 dB and identity -0.002 on the pitch-fixed tracking, a neutral frame's mouth +2.8 dB on synthetic subjects with an open-mouthed input, +1 ms a frame; docs/model-card-log.md "Expression-aware view blending"; model/viewblend.py ExpressionPenalty)
    view_blend_surface_only: bool = True  # record the per-view data (and so blend) only for avatars reconstructed on a tracked head surface (on the network-depth path tau 20 lowered held-out synthetic PSNR; docs/model-card-log.md)
    mirror_views: bool = True  # reconstruct() on a tracked head surface in replace mode (ict53): add the left-right mirror of every input view turned by >= mirror_min_yaw_deg as a virtual view of the unseen side of the head (model/mirror.py; docs/model-card-log.md)
    mirror_min_yaw_deg: float = 30.0  # ... only views whose camera is turned at least this far from frontal, degrees (a near-frontal mirror doubles an asymmetric face)
    mirror_blend_offset_deg: float = 40.0  # ... view blending counts each mirrored view this many degrees further from the render camera than it is (real photos keep precedence near their own cameras; 0 = none; 40 chosen in docs/model-card-log.md, "Why the 40° offset"; model/viewblend.py offsets)
    mirror_midline_m: float = 0.0  # ... drop the mirrored Gaussians within this many metres of the head's sagittal plane (0 = keep them; model/mirror.py near_midline)
    mirror_drop_seen_deg: float = 0.0  # ... drop the mirrored Gaussians whose point a real view sees (inside its matte, unoccluded) at an incidence below this many degrees (0 = keep them all; model/mirror.py seen_by_views)
    flow_register: bool = False  # reconstruct() on a tracked head surface ("replace"): before the network sees them, resample each real input view's image along a dense optical flow (OpenCV DIS) that moves its texture onto where its neighbour view (chained from the most frontal one) sees it through the tracked surface, faded to 0 outside the views' overlap (model/flowreg.py register_views; mirrored views are built from the registered images); off by default: measured neutral, real-photo leave-one-out identity 0.529 both ways, PSNR -0.06 / -0.01 / -0.08 dB, own cameras -0.2 to -0.3 dB (docs/model-card-log.md "Registering the views' textures by optical flow")
    flow_register_clip_px: float = 4.0  # ... the largest flow, pixels at an image side of 256 (scaled with the input: 2 px of the tiny model's 128² inputs); must be > 0
    photo_shapes: str = "off"  # reconstruct() on a tracked head surface ("replace"): what each input pixel's Gaussian keeps of the photo (model/surface.py photo_pixel_shapes): "colour_opacity" (the pixel's own colour, the decoder's colour residual dropped, and opacity 1 inside the view's matte), "colour_opacity_scale" (also scales x PHOTO_SHAPES_SCALE, 0.75); "off" (the default: "colour_opacity_scale" lowered real-photo leave-one-out identity 0.512 -> 0.498 but cost 0.13 / 0.28 dB on two of three sets and shows the 128² splat grid as a stipple at novel cameras; at the input cameras identity 0.426 -> 0.383; "colour_opacity" raised identity to 0.529; docs/model-card-log.md "The Gaussians' shapes on real photos, and expression-aware blending, after the anchor")
    mirror_under_below_chin: bool = True  # reconstruct() with mirrored views: the mirrored views' Gaussians lower than the tracked chin (their neck, collar, shoulders: the torso is not left-right symmetric about a turned head) are drawn under the other Gaussians in every frame, as the off-head ones are (ViewBlend.under; model/surface.py below_chin; on by default: real-photo leave-one-out PSNR +0.07 / +0.06 / +0.02 dB, identity as before, docs/model-card-log.md "Skin and off-colour smears over the shoulders")

    @property
    def channels(self) -> int:
        """Raw channels per pixel: depth 1 + rgb 3 + quat 4 + scale 3 + opacity 1 + feature."""
        return 12 + self.feature_dim


@dataclass
class DeformConfig:
    """Deformation MLP: [feature, PE(xyz), expression] -> (dxyz, drgb) per Gaussian."""

    hidden_size: int = 256  # width of the hidden layers (paper: 256)
    num_layers: int = 6  # hidden layers, each Linear + LeakyReLU (paper: 6)
    pe_freqs: int = 6  # sinusoidal frequencies 2^k * pi, k < pe_freqs, per coordinate
    pe_scale: float = 4.0  # xyz (metres) is multiplied by this before the encoding (head ~ [-0.6, 0.6])
    negative_slope: float = 0.01  # LeakyReLU slope
    # Expression prior (issue 16, model/prior.py): each canonical Gaussian takes the blendshape
    # displacement of its nearest point on a head surface fitted to the avatar; the MLP is a residual.
    prior: bool = False  # paper: the paper's pure MLP; tiny: on
    prior_fade: tuple[float, float] = (0.006, 0.025)  # metres from the surface: full weight, no weight
    mouth_interior: bool = True  # with the prior: teeth/gums/mouth-socket Gaussians in every avatar
    # with the prior (ict53): an opaque shell on the fitted head's back and scalp (model/prior.py,
    # ``back_shell``): no input sees the back of the head, which was hollow and showed the face from behind
    back_shell: bool = True
    # with the prior (ict53): the same kind of shell under the jaw and on the front of the neck, bound
    # to follow the expression prior (``chin_shell``): a pitched-up view sees the jaw's underside that no
    # input does (docs/model-card-log.md "Under the chin")
    chin_shell: bool = True
    # with the prior (ict53): the same kind of shell under the cheeks beside the mouth (``cheek_shell``)
    # in every avatar. Off: a cheek thinned by refinement showed the mouth interior's red through it
    # from a side, so refinement that changes opacities adds the shell to the avatars it refines
    # (``RefineConfig.cheek_shell``); in every avatar dlib reads never-refined avatars' smiles as
    # narrower (held-out mouthSmile response 0.76 -> 0.68, under issue 16's 0.7; docs/model-card-log.md
    # "Red dots on the cheek")
    cheek_shell: bool = False
    # with the prior (ict53): the same kind of shell under the face in every avatar (``face_shell``):
    # "forehead" (the default: the forehead between the brows and the back shell), "upper" (also the
    # nose, cheekbones and brows, clear of the eyes), "off". Seen from in front, turned photos' pixel
    # Gaussians leave gaps there, through which the back shell showed as a dark hatched patch; "upper"
    # also closes the nose's, but on real photos it washed the faces out (leave-one-out identity
    # 0.446 -> 0.485; docs/model-card-log.md "A shell under the face")
    face_shell: str = "forehead"
    # with the prior: relight what an expression moves (model/prior.py, ``shading_basis``): a photo's
    # baked light otherwise stays on a moved surface (no smile creases, an evenly lit dropped lip)
    prior_shading: bool = True
    # with the prior: each bound Gaussian turns with its triangle of the fitted head (model/prior.py,
    # ``PriorRuntime.rotation``), faded by its binding weight. Off by default (tiny too): on 4 x 20
    # held-out subjects it moved the dlib responses by dlib's jitter and cost 0.10-0.14 dB of mouth
    # PSNR on jawOpen (docs/model-card-log.md); off, the prior moves centres only
    prior_rotate: bool = False
    # avatars whose per-view data holds each input view's expression (reconstructed on a tracked head
    # surface, ``ViewBlend.expressions``): the deformation MLP's residual is taken relative to the
    # residual at the Gaussian's own view's expression, MLP(z) - MLP(z_view), so that at its photo's
    # expression each Gaussian lies where the tracked head put it, on its own pixel. The MLP learned a
    # constant offset (2 mm median, 1 cm at the nose) for the network's depth; on the tracked surface it
    # tore holes beside the nose that the back shell showed through (docs/model-card-log.md "The dark
    # blot beside the nose")
    anchor_residual: bool = True
    flame_model: str | None = None  # flame120 models: FLAME model file (else $FASTGHA_FLAME_MODEL)


@dataclass
class FastGHAConfig:
    """The whole model. ``name`` and ``expression_space`` travel with avatars and the server."""

    name: str = "paper"  # preset name (or a user name for a trained variant)
    expression_space: str = "flame120"  # fastgha_core.expressions space: "flame120" or "ict53"
    expression_dim: int = 120  # E, length of an expression code (must match the space)
    input_size: int = 512  # S: input images and Gaussian maps are S x S
    render_size: int = 512  # default training/rendering resolution
    max_views: int = 8  # reconstruct() accepts 1..max_views images
    dino: DinoConfig = field(default_factory=DinoConfig)
    vae: VAEConfig = field(default_factory=VAEConfig)
    transformer: TransformerConfig = field(default_factory=TransformerConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    gaussians: GaussianHeadConfig = field(default_factory=GaussianHeadConfig)
    deform: DeformConfig = field(default_factory=DeformConfig)

    def __post_init__(self) -> None:
        self.validate()

    @property
    def token_channels(self) -> int:
        """Input token width: C_d + C_e + 6 (Plücker)."""
        return self.dino.out_channels + self.vae.latent_channels + 6

    @property
    def encoders_frozen(self) -> bool:
        return self.dino.frozen and self.vae.frozen

    def validate(self) -> None:
        s = self.input_size
        if s % 8 != 0 or s % self.dino.patch_size != 0:
            raise ValueError(f"input_size must be divisible by 8 and by the DINO patch size {self.dino.patch_size}, got {s}")
        if len(self.vae.block_out_channels) != 4 or len(self.decoder.block_out_channels) != 4:
            raise ValueError(
                "VAE encoder and decoder need 4 blocks (H/8 latents), got "
                f"{list(self.vae.block_out_channels)} and {list(self.decoder.block_out_channels)}"
            )
        if bad := [i for i in self.dino.feature_layers if not 1 <= i <= self.dino.num_layers]:
            raise ValueError(f"dino.feature_layers must lie in [1, {self.dino.num_layers}], got {bad}")
        if (self.dino.hidden_size // self.dino.num_heads) % 4 != 0 or self.dino.hidden_size % self.dino.num_heads:
            raise ValueError(f"DINO head dim must be an integer divisible by 4, got {self.dino.hidden_size}/{self.dino.num_heads}")
        if self.transformer.hidden_size % self.transformer.num_heads:
            raise ValueError(
                f"transformer.hidden_size {self.transformer.hidden_size} not divisible by num_heads {self.transformer.num_heads}"
            )
        if not 1 <= self.max_views:
            raise ValueError(f"max_views must be >= 1, got {self.max_views}")
        from .expressions import get_space

        dim = len(get_space(self.expression_space).names)  # ValueError naming the spaces when unknown
        if self.expression_dim != dim:
            raise ValueError(f"expression_dim must be {dim}, the length of expression_space {self.expression_space!r}'s codes, got {self.expression_dim}")
        _validate_gaussians(self.gaussians)
        _validate_deform(self.deform)

    # ------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FastGHAConfig":
        return _from_dict(cls, data, "config")

    def copy(self, **changes: Any) -> "FastGHAConfig":
        return dataclasses.replace(copy.deepcopy(self), **changes)


# ------------------------------------------------------------ field ranges
# The allowed values of the string options; each is also checked where it is used (model/fastgha.py,
# model/surface.py), which is only on a tracked head surface: here a typo fails when the config loads.
EDGE_MODES = ("colour", "fade")
NECK_CYLINDER_MODES = ("off", "off_head", "below_ring")
OFF_HEAD_HULL_MODES = ("off", "entry", "nearest", "middle")
OFF_HEAD_SMOOTH_AXES = ("vertical", "both")  # = model/surface.py's
OFF_HEAD_DRAW_MODES = ("off", "behind", "drop", "sharp", "headon_sharp", "cover_sharp", "under")  # = model/surface.py's
PHOTO_SHAPES_MODES = ("off", "colour_opacity", "colour_opacity_scale")  # = model/surface.py's
FACE_SHELL_REGIONS = ("off", "forehead", "upper")  # DeformConfig.face_shell (model/prior.py face_shell_vertices)
MAX_VIEW_BLEND_TAU_DEG = 360.0  # = fastgha_core.commands.MAX_VIEW_BLEND_TAU_DEG (the server's bound on its override)


def _in_range(where: str, value: Any, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
              hi_open: bool = False, integer: bool = False, note: str = "") -> None:
    """``ValueError`` naming ``where`` and the allowed range unless ``value`` is a finite number in it
    (``[lo, hi]``, an end left out is unbounded, ``lo_open`` / ``hi_open`` exclude that end;
    ``integer``: an ``int``). ``note`` says what the value means (e.g. "0 = off")."""
    import math
    import numbers

    if integer:
        ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    else:
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if ok:
        return
    kind = "an integer" if integer else "a number"
    if lo is not None and hi is not None:
        rng = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    elif lo is not None:
        rng = f"{'>' if lo_open else '>='} {lo:g}"
    elif hi is not None:
        rng = f"{'<' if hi_open else '<='} {hi:g}"
    else:
        rng = "(finite)"
    raise ValueError(f"{where} must be {kind} {rng}{f' ({note})' if note else ''}, got {value!r}")


def _one_of(where: str, value: Any, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"{where} must be one of {list(allowed)}, got {value!r}")


def _switches(where: str, section) -> None:
    """``ValueError`` unless each of ``section``'s on/off fields (those whose default is a bool) holds
    ``true`` / ``false``: a string such as ``"false"`` in a config.json is truthy and used to turn the
    switch on."""
    for f in dataclasses.fields(section):
        if isinstance(f.default, bool) and not isinstance(getattr(section, f.name), bool):
            raise ValueError(f"{where}{f.name} must be true or false, got {getattr(section, f.name)!r}")


def _validate_gaussians(g: GaussianHeadConfig) -> None:
    """The ranges of ``GaussianHeadConfig``'s numeric and string fields (see each field's comment).
    Several read 0 as "off"; a negative value used to turn such a term off silently."""
    w = "gaussians."
    _switches(w, g)
    _in_range(w + "feature_dim", g.feature_dim, 0, integer=True)
    _in_range(w + "depth_range", g.depth_range, 0, lo_open=True, note="metres either side of the camera distance")
    _in_range(w + "min_scale_px", g.min_scale_px, 0, lo_open=True, note="pixel footprints")
    _in_range(w + "max_scale_px", g.max_scale_px, g.min_scale_px, note="pixel footprints, at least min_scale_px")
    _in_range(w + "prune_opacity", g.prune_opacity, 0, 1, hi_open=True, note="0 = keep all")
    _in_range(w + "depth_parity_sigma", g.depth_parity_sigma, 0, note="pixels; 0 = off")
    _in_range(w + "edge_margin_px", g.edge_margin_px, 0, note="pixels; 0 = off")
    _one_of(w + "edge_mode", g.edge_mode, EDGE_MODES)
    _in_range(w + "coverage_target", g.coverage_target, 0, 1, note="a fraction of each matte; 0 = off")
    _one_of(w + "neck_cylinder", g.neck_cylinder, NECK_CYLINDER_MODES)
    _one_of(w + "off_head_hull", g.off_head_hull, OFF_HEAD_HULL_MODES)
    _in_range(w + "off_head_extrude_m", g.off_head_extrude_m, 0, 0.3, note="metres behind the ears' plane; 0 = off")
    _in_range(w + "off_head_smooth", g.off_head_smooth, 0, 1, note="a fraction of the input's side; 0 = off")
    _one_of(w + "off_head_smooth_axis", g.off_head_smooth_axis, OFF_HEAD_SMOOTH_AXES)
    _in_range(w + "off_head_smooth_hold", g.off_head_smooth_hold, 0, 1, note="a fraction of the input's side; 0 = none")
    _one_of(w + "off_head_draw", g.off_head_draw, OFF_HEAD_DRAW_MODES)
    _in_range(w + "head_on_colour_tol", g.head_on_colour_tol, 0, 1, note="a colour difference, channels in 0..1; 0 = off")
    _in_range(w + "head_on_gain_deg", g.head_on_gain_deg, 0, 180, note="degrees")
    _in_range(w + "head_on_tau_scale", g.head_on_tau_scale, 0, lo_open=True, note="a fraction of view_blend_tau_deg")
    _in_range(w + "grazing_stretch", g.grazing_stretch, 0, note="0 = off")
    _in_range(w + "stereo_depth_mm", g.stereo_depth_mm, 0, note="millimetres; 0 = off")
    _in_range(w + "grazing_edge_px", g.grazing_edge_px, 0, integer=True, note="pixels; 0 = everywhere")
    _in_range(w + "grazing_keep_features_mm", g.grazing_keep_features_mm, 0, note="millimetres; 0 = off")
    _in_range(w + "grazing_min_ratio", g.grazing_min_ratio, 0, note="pixel footprints")
    _in_range(w + "view_blend_tau_deg", g.view_blend_tau_deg, 0, MAX_VIEW_BLEND_TAU_DEG, note="degrees; 0 = off")
    _in_range(w + "view_blend_expr_mm", g.view_blend_expr_mm, 0, note="millimetres; 0 = off")
    _in_range(w + "mirror_min_yaw_deg", g.mirror_min_yaw_deg, 0, 180, note="degrees from frontal")
    _in_range(w + "mirror_blend_offset_deg", g.mirror_blend_offset_deg, 0, note="degrees; 0 = none")
    _in_range(w + "mirror_midline_m", g.mirror_midline_m, 0, note="metres; 0 = keep them")
    _in_range(w + "mirror_drop_seen_deg", g.mirror_drop_seen_deg, 0, 90, note="an incidence angle in degrees; 0 = keep them all")
    _in_range(w + "flow_register_clip_px", g.flow_register_clip_px, 0, lo_open=True, note="pixels at an image side of 256")
    _one_of(w + "photo_shapes", g.photo_shapes, PHOTO_SHAPES_MODES)


def _validate_deform(d: DeformConfig) -> None:
    """The ranges of ``DeformConfig``'s numeric fields (see each field's comment)."""
    w = "deform."
    _switches(w, d)
    _in_range(w + "hidden_size", d.hidden_size, 1, integer=True)
    _in_range(w + "num_layers", d.num_layers, 1, integer=True, note="hidden layers")
    _in_range(w + "pe_freqs", d.pe_freqs, 0, integer=True, note="0 = xyz only")
    _in_range(w + "pe_scale", d.pe_scale, 0, lo_open=True)
    _in_range(w + "negative_slope", d.negative_slope, 0, 1, hi_open=True, note="the LeakyReLU slope; the in-place activation's backward needs >= 0")
    fade = d.prior_fade
    if not isinstance(fade, (tuple, list)) or len(fade) != 2:
        raise ValueError(f"deform.prior_fade must be two distances in metres (full weight up to, no weight beyond), got {fade!r}")
    _in_range(w + "prior_fade[0]", fade[0], 0, note="metres from the surface with full prior weight")
    _in_range(w + "prior_fade[1]", fade[1], fade[0], note="metres from the surface with no prior weight, at least prior_fade[0]")
    _one_of(w + "face_shell", d.face_shell, FACE_SHELL_REGIONS)


def check_field_types(cls, data: dict, where: str) -> None:
    """``ValueError`` naming ``where.field`` when a JSON value in ``data`` cannot be the field's type,
    judged by the field's default: ``true``/``false`` for a bool, an integer for an int, a number
    for a float, a string for a str, a list of numbers for a tuple of numbers, an object for a
    nested section; fields whose default is None take anything. A string such as ``"2"`` for an int
    used to pass and fail minutes later, deep in training, with a ``TypeError``."""
    import numbers

    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if isinstance(default, bool):
            ok, kind = isinstance(value, bool), "true or false"
        elif isinstance(default, int):
            ok, kind = isinstance(value, numbers.Integral) and not isinstance(value, bool), "an integer"
        elif isinstance(default, float):
            ok, kind = isinstance(value, numbers.Real) and not isinstance(value, bool), "a number"
        elif isinstance(default, str):
            ok, kind = isinstance(value, str), "a string"
        elif isinstance(default, tuple) and all(isinstance(v, numbers.Real) for v in default):
            ok = isinstance(value, (list, tuple)) and all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in value)
            kind = "a list of numbers"
        elif dataclasses.is_dataclass(default):
            ok, kind = isinstance(value, (dict, type(default))), "an object of fields"
        else:
            continue
        if not ok:
            raise ValueError(f"{where}.{f.name} must be {kind}, got {value!r}")


def _from_dict(cls, data: Any, where: str):
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object, got {type(data).__name__}")
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {unknown}; expected some of {sorted(names)}")
    kw = {}
    for key, value in data.items():
        default = names[key].default_factory() if names[key].default_factory is not dataclasses.MISSING else names[key].default
        if dataclasses.is_dataclass(default):
            kw[key] = _from_dict(type(default), value, f"{where}.{key}")
        elif isinstance(default, tuple):
            kw[key] = tuple(value)
        else:
            kw[key] = value
    return cls(**kw)


def _paper() -> FastGHAConfig:
    return FastGHAConfig()


def _tiny() -> FastGHAConfig:
    return FastGHAConfig(
        name="tiny",
        expression_space="ict53",
        expression_dim=53,
        input_size=128,
        render_size=128,
        dino=DinoConfig(
            hidden_size=96,
            num_layers=4,
            num_heads=4,
            intermediate_size=384,
            patch_size=16,
            num_register_tokens=4,
            feature_layers=(2, 4),
            out_channels=64,
            frozen=False,
        ),
        vae=VAEConfig(block_out_channels=(32, 64, 64, 64), layers_per_block=1, norm_num_groups=16, frozen=False),
        transformer=TransformerConfig(hidden_size=192, num_layers=4, num_heads=4),
        decoder=DecoderConfig(block_out_channels=(32, 64, 64, 64), layers_per_block=1, norm_num_groups=16, init_from_vae=False),
        # Pixel-aligned priors for a CPU training budget (~2k steps): each Gaussian starts at its own
        # input pixel's colour (rgb_residual) and background pixels make no Gaussians
        # (foreground_opacity). Without them, 1000 steps still painted one average skin colour, the
        # head being carried by background-pixel Gaussians; with them, step 60 beat step 1000.
        gaussians=GaussianHeadConfig(feature_dim=32, prune_opacity=0.005, rgb_residual=True, foreground_opacity=True),
        deform=DeformConfig(hidden_size=48, num_layers=4, pe_freqs=4, prior=True),  # ~8 ms/frame fp32 at 65k Gaussians on 2 cores
    )


# Read-only templates; get_preset() hands out copies.
PRESETS: dict[str, FastGHAConfig] = {"paper": _paper(), "tiny": _tiny()}


def get_preset(name: str) -> FastGHAConfig:
    """A fresh copy of the named preset (``"paper"`` or ``"tiny"``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; expected one of {sorted(PRESETS)}")
    return copy.deepcopy(PRESETS[name])
