"""Expression prior from a linear head model, the mouth interior (issue 16) and the back of the head (issue 17).

The deformation MLP alone learns expressions slowly (a CPU budget of a few thousand steps moved the
chin 16 mm for ``jawOpen`` = 1 where the head model moves it 42 mm). The prior gives every
canonical Gaussian the blendshape displacement of its nearest point on a head surface fitted to the
avatar; the MLP then predicts a residual on top.

Pieces (all numpy/torch on CPU, no learning):

- ``HeadBasis``: a linear head model in our axes (metres, +x subject's left, +y up, +z out of the
  face): neutral ``[Nv, 3]``, identity modes ``[K, Nv, 3]``, expression blendshapes ``[E, Nv, 3]``,
  the triangles Gaussians bind to and the vertex ids the fit uses. ``load_basis("ict53")`` reads the
  shipped ICT-FaceKit model; ``load_basis("flame120", path)`` reads a FLAME model file given by the
  user (FLAME's blendshapes cannot ship).
- ``fit_head(points, basis)``: trimmed ICP of identity modes + a rigid transform (scale optional) against the
  canonical Gaussian centres (model vertex -> nearest Gaussian correspondences).
- ``bind(points, fit, basis)``: each point's nearest triangle of the fitted surface (barycentric
  coordinates of the clamped projection) and a fade weight ``1 - smoothstep((d - d0) / (d1 - d0))``
  of its distance ``d``, so hair, ears and shoulders far from the surface do not follow the lips.
- ``PriorBinding``: the per-Gaussian result ``vertex_ids [N, 3]``, ``bary [N, 3]``, ``weight [N]``
  plus the fit (``transform [4, 4]`` = scale * rotation | offset, ``identity [K]``); saved in the
  avatar file. ``displacement(z)`` -> ``[N, 3]`` (or ``[B, N, 3]``) per frame through a compact basis
  over the vertices actually used (``PriorRuntime``).
- ``shading_basis(identity, basis)``: per blendshape and vertex, the relative brightness change of the
  fitted head under the light baked into the avatar's colours (``estimate_light``; the generic
  ``SHADE_AMBIENT``, ``SHADE_LIGHT`` when it cannot be told); ``PriorRuntime.shading(z)``
  gathers it like the displacement into a colour factor for the reconstructed Gaussians, whose
  colours carry the photo's light baked in at the neutral pose.
- ``PriorRuntime.rotation(z)`` (config ``deform.prior_rotate``, off by default): each bound Gaussian's
  covariance turns with its triangle of the fitted head (the triangle's frame on the neutral and the
  displaced head), faded by its weight; from the binding alone, nothing more is saved.
- ``mouth_interior(fit, basis)``: Gaussians on the teeth (the lower row every vertex, ``TEETH_STEP``;
  the upper every 2nd, ``TEETH_UPPER_STEP``), gums/tongue
  and mouth-socket meshes of the fitted head, coloured as the synthetic renderer shows them
  (``INTERIOR_SHADE``; the front teeth ``teeth_front_color``, the upper row darker) and set back behind
  the avatar's own lips (``interior_inset``), bound to their own vertex (so they follow the jaw), with
  an opacity gate that is 0 while the lips are closed; and Gaussians on the upper eyelids, coloured
  like the avatar's skin, and on the upper lashes, dark (the avatar's darkest colours at the open
  eye's upper lid), that appear as a blink closes the lids (``gate_factors``); and thin dark
  Gaussians on the upper lip's underside, the seam between closed lips (``LIP_SEAM_NY``), moved to
  where the avatar's own lip colours put it (``_seam_shift``), that fade as the mouth opens.
- ``hide_open_lips(binding, ...)``: the reconstructed Gaussians near the lips from input photos whose
  (tracked) expression opens the mouth fade out as the avatar's mouth opens: undone onto the closed
  lips, those photos' teeth and mouth gap lined the opening (``open_mouth_views``).
- ``back_shell(fit, basis)``: flat, opaque, ungated Gaussians on the fitted head's skin behind the
  ears and above the hairline, a few mm inside it and coloured from the avatar next to them: no
  input photo sees the back of the head, which was otherwise hollow and showed the face from behind.
- ``chin_shell(fit, basis)``: the same discs under the jaw and on the front of the neck, bound to
  follow the expression prior there (the jaw's underside moves with jawOpen): a pitched-up view sees
  that skin, which no less pitched input does (``DeformConfig.chin_shell``).
- ``face_shell(fit, basis, region)``: the same discs under the forehead below the back shell (or
  the whole upper face clear of the eyes), bound to follow the expression prior: seen from in
  front, the turned photos' pixel Gaussians leave gaps there and the back shell showed through them
  as a dark hatched patch (``DeformConfig.face_shell``).
"""

from __future__ import annotations

import functools
import os
import math
from dataclasses import dataclass
from pathlib import Path
import warnings

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "HeadBasis",
    "HeadFit",
    "PriorBinding",
    "PriorRuntime",
    "load_basis",
    "fit_head",
    "bind",
    "mouth_interior",
    "teeth_front_color",
    "interior_inset",
    "back_shell",
    "back_shell_vertices",
    "chin_shell",
    "chin_shell_vertices",
    "face_shell",
    "face_shell_vertices",
    "mouth_gate_vector",
    "open_mouth_views",
    "hide_open_lips",
    "lip_hide_group",
    "generic_fit",
    "gate_factors",
    "shading_basis",
    "shading_at",
    "ShadeLight",
    "estimate_light",
    "FLAME_ENV",
]

FLAME_ENV = "FASTGHA_FLAME_MODEL"

# Mouth-opening blendshapes (ict53 names) and how much each opens the lips, for the interior's gate.
_MOUTH_OPENING = {
    "jawOpen": 1.0,
    "mouthFunnel": 0.4,
    "mouthLowerDown_L": 0.3,
    "mouthLowerDown_R": 0.3,
    "mouthUpperUp_L": 0.3,
    "mouthUpperUp_R": 0.3,
    "mouthStretch_L": 0.15,
    "mouthStretch_R": 0.15,
}
GATE_START, GATE_FULL = 0.04, 0.25  # gate(z) = smoothstep((g.z - START) / (FULL - START))
# Closed-lid lashes: ICT-FaceKit's upper-lash vertices (those the blink moves > 4 mm), every 2nd,
# as 1.3 mm Gaussians; their colour is the avatar's own (``_lash_color``), at most LASH_MAX_LUMA
# times as bright as the closed lid's skin; LASH_DEFAULT without an avatar to take it from.
LASH_TRAVEL, LASH_STEP, LASH_SCALE = 0.004, 2, 0.0013
TEETH_SCALE = 0.0012  # metres, the teeth Gaussians' scale (gums and socket: 0.9 * 2.2 mm)
# The mouth interior's brightness (teeth, gums/tongue, socket): factors on albedo-like colours so that
# they match how the synthetic renderer shows the inside of an open mouth (its albedo under the rig's
# lights), not the bare albedo: its mean luma over that of the bare colours, ict53 vertices at
# jawOpen = 1, 30 training subjects (``bench/interior_colors.py``). Unlit, the interior rendered
# 1.5-1.9x too bright: a pale red opening whose edge against the lips dlib placed inside the opening,
# reading the held-out jawOpen lip gap at 0.60-0.85 of the truth's (issue 16; docs/model-card-log.md).
INTERIOR_SHADE = (0.65, 0.69, 0.53)
# The lower teeth's colour where they meet the lips (their front; deeper teeth darken as before, ``1 - 0.7 *
# depth``): TEETH_FRONT_LUMA, the mean luma of the brightest 30% of the teeth's pixels that the
# synthetic renderer shows when the lips part off the teeth (0.647, 10 training subjects, frontal;
# ``bench/interior_colors.py``, ``visible_teeth``), with TEETH_CHROMA, the hue (RGB over luma) of the teeth in
# the real sets' photos that show them (studio-4 and phone-5's smiles: 1.15 / 0.96 / 0.81 and
# 1.13 / 0.96 / 0.86). Until 2026-12-01 the front teeth were INTERIOR_SHADE[0] * (0.86, 0.83, 0.75):
# luma 0.54 and a near-neutral grey, which next to the red mouth and warm skin of real photos read as
# a teal cast ("greenish teeth"; docs/model-card-log.md "Teeth on real avatars").
TEETH_FRONT_LUMA = 0.65
TEETH_CHROMA = (1.14, 0.96, 0.83)
# Every TEETH_STEP-th lower-row teeth vertex of ICT-FaceKit carries a Gaussian (1: all 2204, about 1 mm
# apart): at every 2nd (1.4 mm apart) most of the row hid behind the gums' and socket's larger Gaussians
# and the lower teeth showed as 3-5 grey dots instead of a row
TEETH_STEP = 1
# The upper row (the teeth jawOpen does not move): every TEETH_UPPER_STEP-th vertex (1104 of 2208), front
# luma TEETH_UPPER_LUMA, the same hue. At jawOpen the synthetic truth shows almost no upper teeth (its
# upper lip covers them: median 0, at most 19 pixels of them in frontal and 30° renders at 512² of 10
# training subjects; the lower teeth 73 and 657), while ours drew a light band there, under the avatar's
# thin upper lip, and dlib put the inner upper lip below it: with the upper row like the lower (every
# vertex, luma 0.65; 2026-12-01) draw B's held-out jawOpen response at 512² fell 0.764 -> 0.660 (bar
# 0.70). Sparser and darker: 0.738 (every 2nd vertex at 0.65: 0.709; every vertex at 0.35: 0.724). Not
# the lower row: it alone at luma 0.54 read 0.663 (docs/model-card-log.md "Teeth on real avatars",
# 2026-12-01 night). Real avatars' upper teeth stay hidden under their upper lip either way.
TEETH_UPPER_STEP = 2
TEETH_UPPER_LUMA = 0.45
# The mouth interior moves back as deep as the avatar's lips sit behind the fitted lips (``interior_inset``),
# at most INTERIOR_INSET_MAX, measured on at least INSET_MIN_POINTS lip Gaussians.
INTERIOR_INSET_MAX = 0.006  # metres
INSET_MIN_POINTS = 20
LASH_MAX_LUMA = 0.45
LASH_DEFAULT = (0.10, 0.08, 0.07)
_LUMA = np.array([0.299, 0.587, 0.114], np.float32)  # Rec. 601 luma weights
# Expression shading: a reconstruction bakes the photo's light into its colours, so a moved surface
# keeps the shade of its neutral pose (a smile's creases and a dropped lower lip stay as lit as
# before). The prior relights the change: each vertex's brightness ambient + (1 - ambient) *
# max(n . light, 0) at the expression over that at neutral, on the fitted head in the head model's
# own frame. The light is the one baked into the avatar's colours (``estimate_light``); where that
# cannot be told, the generic one below: the synthetic rig's mean key light (azimuth +-75 deg,
# elevation -5..60 deg: frontal, ~27 deg above; photos are mostly lit from above too) and the ambient
# its share of the light (ambient 0.2-0.45 against a key of 0.7-1.1). Linear in the expression (see
# ``shading_basis``).
SHADE_AMBIENT = 0.3
SHADE_LIGHT = np.array([0.0, 0.5, 1.0], np.float64) / np.sqrt(1.25)
SHADE_RANGE = (0.5, 1.5)  # the per-Gaussian colour factor is clamped to this
# The brightness ratio is one of linear light; the Gaussians' colours are sRGB (gamma 2.2), so the
# colour factor of one blendshape at weight 1 is ratio ** (1 / SHADE_GAMMA). Applied to the sRGB
# colours unconverted, the ratio relit 2.2x too strongly (in log): a jawOpen brightened the far jaw's
# underside to the clamp and darkened the chin, and on training subjects the per-vertex error against
# the synthetic renderer's own colour ratio was above that of no shading at all (docs/model-card-log.md).
SHADE_GAMMA = 2.2
# The avatar's own light (``estimate_light``): from at least LIGHT_MIN_POINTS skin Gaussians, the
# LIGHT_KEEP best-fitting share of them, a directional part of at least LIGHT_MIN_CONTRAST of the
# constant one (else the generic light above), the ambient share clipped to LIGHT_AMBIENT.
LIGHT_MIN_POINTS = 300
LIGHT_KEEP = 0.8
LIGHT_MIN_CONTRAST = 0.05
LIGHT_AMBIENT = (0.1, 0.8)
LIGHT_STEPS_DEG = (8.0, 4.0, 2.0, 1.0)  # the direction's refinement (azimuth, elevation), +-2 steps each

# Lips of input photos with an open mouth (``hide_open_lips``): a view whose tracked expression opens
# the mouth gate (``gates[0] @ z``) above OPEN_VIEW_GATE has its reconstructed Gaussians within
# LIP_RADIUS of the lips (the fitted head's 20 lip landmarks, ``HeadBasis.lip_landmarks``) fade out as
# the avatar's mouth opens; the view with the most closed mouth always keeps its lips.
OPEN_VIEW_GATE = 0.1
LIP_RADIUS = 0.008  # metres

# The lip seam (issue 16, the smile): the ground-truth renderer draws a sharp dark line between the
# closed lips (gone as they part: ``lip_hide_group``), the upper lip's underside (normals facing down, away from any light from above); a
# smile stretches it out to the corners. A few-view reconstruction has no such line (0 dark pixels
# where the truth has 1-650, 512²), and dlib then reads the smile's corners short. Always-on
# Gaussians on that underside: ICT-FaceKit lip vertices with a neutral normal's y below LIP_SEAM_NY,
# between LIP_SEAM_BAND (metres, below / above the inner-lip landmarks' mean height), within
# LIP_SEAM_REACH of an inner-lip landmark and inside the mouth corners (196 points), LIP_SEAM_SCALE
# in the basis and drawn LIP_SEAM_AXES wide; coloured like the avatar's own lips there (median of the LIP_SEAM_K nearest solid Gaussians)
# times their brightness against the lips' front under the generic light, ** (LIP_SEAM_CONTRAST/2.2)
# (sRGB; LIP_SEAM_CONTRAST < 1 draws it lighter: the blurred reconstruction's seam is wider than the
# truth's 1-px line, and at full contrast it cost 0.23 dB of the smile's mouth PSNR, training seeds 0-29).
LIP_SEAM_NY = -0.5
LIP_SEAM_BAND = (-0.001, 0.0015)
LIP_SEAM_REACH = 0.012
LIP_SEAM_SCALE = 0.0008
# each seam Gaussian's scales (metres, before the fit's scale) along the head's x (the seam's run),
# y (across it) and z: flat across the seam and stretched along it, so the points join into a thin
# continuous line (isotropic LIP_SEAM_SCALE drew a beaded line of dots at 512², darker and wider than
# the truth's 1-px line); rotated with the fit
LIP_SEAM_AXES = (0.0015, 0.0001, 0.0003)
LIP_SEAM_CONTRAST = 0.75
LIP_SEAM_K = 8
LIP_SEAM_DEFAULT = (0.45, 0.2, 0.18)  # lip red, without an avatar to take it from
# Where the seam sits (``_seam_shift``): the fitted head's lip line is off by -5.8 to +5.6 mm in height
# (training seeds 0-29, 256², the truth's seam vertices against the fitted ones; mean +0.7, sd 2.5), and
# a seam drawn there lies on the avatar's lip instead of between its lips. The avatar's own colours
# place the lips: along the fit's up axis, the opacity-weighted luma of its solid Gaussians within
# LIP_SEAM_COLUMNS of the inner mouth's half-width from its centre and in front of the lips' front less
# LIP_SEAM_DEPTH, smoothed over LIP_SEAM_SMOOTH, is darkest on the upper lip, a few mm above the truth's
# seam vertices (median 2.85 mm; the residual: 0.9 mm mean, against 2.0 mm for the fit). The seam goes
# LIP_SEAM_BELOW under that line, at most LIP_SEAM_MAX_SHIFT from the fit (searched within
# LIP_SEAM_SEARCH of it). 1.5 mm read a higher smile mouth PSNR on those seeds (0.5 / 1.0 / 1.5 / 2.2 /
# 2.85 mm: 22.97 / 23.06 / 23.10 / 23.06 / 22.91 dB; the fitted place 22.72) but a held-out jawOpen of
# 0.69 (B 256²; 0.72 at 2.85 mm, as before the shift): a seam that high reads as parted lips at neutral.
LIP_SEAM_COLUMNS = 0.4
LIP_SEAM_DEPTH = 0.008  # metres
LIP_SEAM_SMOOTH = 0.00075  # metres (Gaussian kernel sd)
LIP_SEAM_SEARCH = 0.006  # metres
LIP_SEAM_BELOW = 0.00285  # metres
LIP_SEAM_MAX_SHIFT = 0.005  # metres
LIP_SEAM_MIN_POINTS = 10
LIP_SEAM_MIN_CONTRAST = 0.02  # luma: a flatter profile leaves the seam where the fit puts it


@dataclass(frozen=True, eq=False)
class HeadBasis:
    """A linear head model (numpy, float32, metres, our axes).

    Attributes:
        space: expression space of ``expression_basis`` (``"ict53"`` / ``"flame120"``).
        neutral: ``[Nv, 3]``; identity_basis: ``[K, Nv, 3]``; expression_basis: ``[E, Nv, 3]``
            (for ``flame120`` the 100 linear coefficients; jaw/eye rotations are left to the MLP).
        bind_faces: ``[F, 3]`` triangles of the fitted surface (its normals drive the fit; Gaussians
            bind to them, except ``mouth_faces``).
        fit_vertices: ``[M]`` vertex ids whose nearest Gaussians drive the fit (front of the face).
        interior_vertices / interior_colors: ``[I]`` ids and ``[I, 3]`` sRGB of the mouth interior.
        interior_spacing: typical distance between neighbouring interior vertices (metres).
    """

    space: str
    neutral: np.ndarray
    identity_basis: np.ndarray
    expression_basis: np.ndarray
    bind_faces: np.ndarray
    fit_vertices: np.ndarray
    interior_vertices: np.ndarray
    interior_colors: np.ndarray
    interior_spacing: float
    gates: np.ndarray  # [G, E] blendshape weights per gate group (0: mouth opening; 1, 2: eyelids)
    gate_ranges: np.ndarray  # [G, 2] (start, full): gate = smoothstep((gates @ z - start) / (full - start))
    interior_group: np.ndarray  # [I] gate group of each interior point
    interior_scale: np.ndarray  # [I] Gaussian scale (metres, before the fit's scale)
    sample_color: np.ndarray  # [I] bool: colour taken from the avatar (nearest Gaussian above the point)
    hide_group: np.ndarray  # [Nv] int8: reconstructed Gaussians bound here fade out with this gate (0: never)
    lash: np.ndarray | None = None  # [I] bool: closed-lid lash points (dark, ``_lash_color``); None: none
    lid_back: np.ndarray | None = None  # [I] bool: the closed lids' backing (``LID_BACK_*``); None: none
    # [F] bool: triangles of ``bind_faces`` inside the mouth (teeth, gums/tongue, socket) that the
    # reconstructed Gaussians do not bind to (``bind``); None: every triangle binds
    mouth_faces: np.ndarray | None = None
    # [L] vertex ids of the lip landmarks (``hide_open_lips``); None: no lip hiding
    lip_landmarks: np.ndarray | None = None
    # [I] bool: lip-seam points (``lip_hide_group``, ``LIP_SEAM_NY``); their ``interior_colors`` hold
    # the brightness factor that multiplies the avatar's lip colour; None: none
    seam: np.ndarray | None = None

    @property
    def gate(self) -> np.ndarray:
        """``[E]`` weights of the mouth-opening blendshapes (gate group 0)."""
        return self.gates[0]

    @property
    def num_expression(self) -> int:
        return int(self.expression_basis.shape[0])


def load_basis(space: str, flame_model: str | Path | None = None) -> HeadBasis:
    """The head basis of an expression space.

    Args:
        space: ``"ict53"`` (shipped ICT-FaceKit model) or ``"flame120"``.
        flame_model: for ``flame120``, a FLAME model file (``.npz`` or an unpickled-able ``.pkl``
            with ``v_template``, ``shapedirs``, ``f``); default: the ``FASTGHA_FLAME_MODEL`` variable.
    Raises:
        FileNotFoundError: ``flame120`` without a FLAME model file.
        ValueError: an unknown space.
    """
    if space == "ict53":
        return _ict_basis()
    if space == "flame120":
        path = flame_model or os.environ.get(FLAME_ENV)
        if not path or not Path(path).is_file():
            raise FileNotFoundError(
                "the expression prior of flame120 models needs FLAME's blendshapes, which FastGHA cannot ship: "
                f"set {FLAME_ENV} to a FLAME model file (.npz or .pkl with v_template, shapedirs, f), "
                f"or turn the prior off (deform.prior = false); got {str(path) if path else 'no file'}"
            )
        return _flame_basis(str(Path(path).resolve()))
    raise ValueError(f"no head basis for expression space {space!r}; expected 'ict53' or 'flame120'")


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@functools.lru_cache(maxsize=1)
def _ict_basis() -> HeadBasis:
    from ..data.appearance import head_regions
    from ..data.headmodel import HEAD_VERTEX_RANGE, HeadModel

    m = HeadModel.load()
    faces = m.visible_faces(eyelashes=True)
    lm = m.neutral[m.landmarks68]
    v = m.neutral
    # Fit on the face skin below the hairline (synthetic hair and real hair both sit off the skull).
    idx = np.arange(HEAD_VERTEX_RANGE[0], 9409)
    brow_y = lm[17:27, 1].max()
    front = idx[(v[idx, 1] < brow_y + 0.015) & (v[idx, 2] > lm[0, 2] - 0.01) & (v[idx, 1] > lm[8, 1] - 0.005)]
    # Mouth interior: teeth, gums/tongue and the mouth socket, with the synthetic albedo's colours.
    reg = head_regions(m)
    inside = (reg.teeth > 0) | (reg.gums > 0) | (reg.mouth_interior > 0)  # [Nv] the mouth's inside
    teeth = np.flatnonzero(reg.teeth > 0)
    gums = np.flatnonzero(reg.gums > 0)
    sock = np.flatnonzero((reg.mouth_interior > 0) & (reg.gums <= 0))
    # Subsample to a few thousand points (every k-th vertex in the archive order keeps them spread).
    jaw_moves = np.linalg.norm(m.expression_basis[m.expression_names.index("jawOpen")], axis=1) > 0.01  # [Nv] the lower jaw
    teeth = np.sort(np.concatenate([teeth[jaw_moves[teeth]][::TEETH_STEP], teeth[~jaw_moves[teeth]][::TEETH_UPPER_STEP]]))
    gums, sock = gums[::2], sock[::2]
    depth_in = np.clip((lm[48:68, 2].max() - v[:, 2]) / 0.045, 0, 1)
    # albedo-like colours darkened by INTERIOR_SHADE: the inside of a mouth is lit far less than the face
    _, sh_g, sh_s = INTERIOR_SHADE  # the teeth take teeth_front_color() instead of INTERIOR_SHADE[0]
    front_c = np.where(jaw_moves[teeth][:, None], teeth_front_color()[None], teeth_front_color(TEETH_UPPER_LUMA)[None])
    teeth_c = front_c * (1.0 - 0.7 * depth_in[teeth])[:, None]
    gum_c = sh_g * np.array([0.62, 0.28, 0.28])[None] * (1.0 - 0.6 * depth_in[gums])[:, None]
    sock_c = sh_s * np.array([0.26, 0.09, 0.09])[None] * (1.0 - 0.6 * depth_in[sock])[:, None]
    ids = np.concatenate([teeth, gums, sock]).astype(np.int64)
    cols = np.concatenate([teeth_c, gum_c, sock_c]).astype(np.float32)
    gates = np.zeros((3, m.num_expression), np.float32)
    for n, w in _MOUTH_OPENING.items():
        gates[0, m.expression_names.index(n)] = w
    # Closed eyelids: the skin the blink blendshapes pull over the eye, as Gaussians that appear as
    # the lids close (a few-view reconstruction has no skin under the open lids to move down).
    groups = [np.zeros(len(ids), np.int64)]
    # teeth splats about as wide as their sampling was (every 2nd vertex, 1.4 mm apart; the lower row
    # every vertex since 2026-12-01, 1.0 mm, TEETH_STEP): at the gums' 2 mm they grew 2-3 mm
    # past the teeth's edges, a white band under the upper lip and a rim over the lower one that dlib
    # took for the inner lips (jawOpen lip-gap change on the real sets +0.005 to +0.015, synthetic
    # response 0.65 -> 0.68)
    scales = [np.concatenate([np.full(len(teeth), TEETH_SCALE), np.full(len(gums) + len(sock), 0.0022 * 0.9)])]
    sample = [np.zeros(len(ids), bool)]
    lid_ids, lash_ids, back_ids = [], [], []
    lash_all = np.flatnonzero(reg.lashes > 0)
    for gi, side in ((1, "L"), (2, "R")):
        k = m.expression_names.index(f"eyeBlink_{side}")
        gates[gi, k] = 1.0
        mv = np.linalg.norm(m.expression_basis[k, :9409], axis=1)
        lid = np.flatnonzero(mv > 0.0025)  # moves > 2.5 mm: the upper lid
        # the upper lashes (the lower ones hardly move): with the lids closed they hang over the
        # lower lid as the dark line a closed eye shows (the synthetic truth's, and a real one's)
        lash = lash_all[np.linalg.norm(m.expression_basis[k, lash_all], axis=1) > LASH_TRAVEL][::LASH_STEP]
        lid_ids.append(lid)
        lash_ids.append(lash)
        groups += [np.full(len(lid), gi), np.full(len(lash), gi)]
        scales += [np.full(len(lid), 0.0022), np.full(len(lash), LASH_SCALE)]
        sample += [np.ones(len(lid), bool), np.ones(len(lash), bool)]
        # the lid's backing (LID_BACK_*): wider discs behind the closed lid that fill the hole the
        # eyeball's fading Gaussians leave around it
        back = lid[::LID_BACK_STEP]
        back_ids.append(back)
        groups.append(np.full(len(back), gi))
        scales.append(np.full(len(back), LID_BACK_SCALE))
        sample.append(np.ones(len(back), bool))
    # Reconstructed Gaussians on the eyeballs fade out as the lids close over them.
    from ..data.headmodel import EYEBALL_VERTEX_RANGE

    hide = np.zeros(m.num_vertices, np.int8)
    eye = np.zeros(m.num_vertices, bool)
    eye[EYEBALL_VERTEX_RANGE[0] : EYEBALL_VERTEX_RANGE[1]] = True
    sides = [np.sign(v[lid, 0].mean()) for lid in lid_ids]
    for gi, sg in zip((1, 2), sides):
        hide[eye & (np.sign(v[:, 0]) == sg)] = gi
    n_mouth = len(ids)
    ids = np.concatenate([ids, *(x for trio in zip(lid_ids, lash_ids, back_ids) for x in trio)]).astype(np.int64)
    lash_flag = np.zeros(len(ids), bool)
    lash_flag[n_mouth:] = np.concatenate([np.r_[np.zeros(len(a), bool), np.ones(len(b), bool), np.zeros(len(c), bool)] for a, b, c in zip(lid_ids, lash_ids, back_ids)])
    back_flag = np.zeros(len(ids), bool)
    back_flag[n_mouth:] = np.concatenate([np.r_[np.zeros(len(a) + len(b), bool), np.ones(len(c), bool)] for a, b, c in zip(lid_ids, lash_ids, back_ids)])
    cols = np.concatenate([cols, np.zeros((len(ids) - n_mouth, 3), np.float32)])
    # the lip seam (LIP_SEAM_NY): on while the lips are closed (``lip_hide_group``: 1 - the mouth gate;
    # with the seam on at an open jaw, B 512²'s jaw read 0.68), its colour factor in interior_colors;
    # first, so that the mouth and lid groups stay last and a frame drops those whose gate is 0
    seam_ids, seam_f = _lip_seam(m, faces, reg)
    ids = np.concatenate([seam_ids, ids]).astype(np.int64)
    lash_flag = np.concatenate([np.zeros(len(seam_ids), bool), lash_flag])
    back_flag = np.concatenate([np.zeros(len(seam_ids), bool), back_flag])
    cols = np.concatenate([np.repeat(seam_f[:, None], 3, 1).astype(np.float32), cols])
    groups.insert(0, np.full(len(seam_ids), 2 * len(gates) - 1))  # lip_hide_group: fades as the lips part
    scales.insert(0, np.full(len(seam_ids), LIP_SEAM_SCALE))
    sample.insert(0, np.zeros(len(seam_ids), bool))
    seam_flag = np.zeros(len(ids), bool)
    seam_flag[: len(seam_ids)] = True
    return HeadBasis(
        space="ict53",
        neutral=m.neutral,
        identity_basis=m.identity_basis[:40],
        expression_basis=m.expression_basis,
        bind_faces=faces,
        fit_vertices=front.astype(np.int64),
        interior_vertices=ids,
        interior_colors=np.clip(cols, 0, 1),
        interior_spacing=0.0022,
        gates=gates,
        gate_ranges=np.array([[GATE_START, GATE_FULL], [0.25, 0.75], [0.25, 0.75]], np.float32),
        interior_group=np.concatenate(groups),
        interior_scale=np.concatenate(scales).astype(np.float32),
        sample_color=np.concatenate(sample),
        hide_group=hide,
        lash=lash_flag,
        lid_back=back_flag,
        mouth_faces=inside[faces].any(1),
        lip_landmarks=np.asarray(m.landmarks68[48:68], np.int64),
        seam=seam_flag,
    )


def teeth_front_color(luma: float | None = None) -> np.ndarray:
    """``[3]`` sRGB of the lower teeth Gaussians nearest the lips: luma ``TEETH_FRONT_LUMA`` (Rec. 601;
    ``luma`` instead when given: the upper row's ``TEETH_UPPER_LUMA``) with the hue ``TEETH_CHROMA``
    (RGB over its luma; see their comments)."""
    c = np.asarray(TEETH_CHROMA, np.float64)
    return ((TEETH_FRONT_LUMA if luma is None else float(luma)) * c / float(c @ _LUMA)).astype(np.float32)


def _lip_seam(m, faces: np.ndarray, reg) -> tuple[np.ndarray, np.ndarray]:
    """The lip seam's vertex ids ``[S]`` on ICT-FaceKit and their brightness factor ``[S]`` against the
    lips' front (generic light, ** (LIP_SEAM_CONTRAST / 2.2)); see ``LIP_SEAM_NY``."""
    from scipy.spatial import cKDTree

    from ..data.headmodel import vertex_normals

    v = m.neutral.astype(np.float64)
    n = vertex_normals(v, faces).astype(np.float64)
    inner = v[m.landmarks68[60:68]]
    yc = inner[:, 1].mean()
    xl, xr = sorted((v[m.landmarks68[48], 0], v[m.landmarks68[54], 0]))
    reach = cKDTree(inner).query(v)[0]
    lips = (reg.lips > 0.5) & (np.arange(len(v)) < 9409)
    sel = lips & (n[:, 1] < LIP_SEAM_NY) & (v[:, 1] > yc + LIP_SEAM_BAND[0]) & (v[:, 1] < yc + LIP_SEAM_BAND[1])
    sel &= (reach < LIP_SEAM_REACH) & (v[:, 0] > xl + 0.002) & (v[:, 0] < xr - 0.002)
    ids = np.flatnonzero(sel)
    d, a = SHADE_LIGHT, SHADE_AMBIENT
    br = a + (1.0 - a) * np.clip(n @ np.asarray(d, np.float64), 0.0, None)
    front = lips & (n[:, 2] > 0.8)
    f = np.minimum((br[ids] / np.median(br[front])) ** (LIP_SEAM_CONTRAST / SHADE_GAMMA), 1.0)
    return ids, f.astype(np.float32)


def _fit_frame(fit: HeadFit) -> tuple[np.ndarray, float]:
    """The fit's rotation ``[3, 3]`` (the nearest one to its linear part) and its scale."""
    M = fit.transform[:3, :3].astype(np.float64)
    u, _, vt = np.linalg.svd(M)
    rot = u @ vt
    if np.linalg.det(rot) < 0:
        rot = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return rot, float(np.cbrt(abs(np.linalg.det(M))))


def _seam_shift(fit: HeadFit, basis: HeadBasis, points: np.ndarray, colors: np.ndarray, opacities: np.ndarray) -> float:
    """How far (metres, along the fitted head's up axis, before its scale) the lip seam moves to sit
    where the avatar's own colours put the lip contact line (``LIP_SEAM_BELOW``). ``points [N, 3]``:
    where the reconstructed Gaussians are drawn at the neutral expression (world, metres), ``colors
    [N, 3]`` sRGB, ``opacities [N]``. 0.0 with no seam, no lip landmarks, fewer than
    ``LIP_SEAM_MIN_POINTS`` solid Gaussians in front of the mouth or a profile flatter than
    ``LIP_SEAM_MIN_CONTRAST``."""
    if basis.seam is None or not basis.seam.any() or basis.lip_landmarks is None or len(points) == 0:
        return 0.0
    rot, s = _fit_frame(fit)
    t = fit.transform[:3, 3].astype(np.float64)
    q = (np.asarray(points, np.float64) - t) @ rot / s  # the fitted head's frame (x left, y up, z forward)
    fv = (fit.vertices.astype(np.float64) - t) @ rot / s
    ys = fv[basis.interior_vertices[basis.seam], 1].mean()
    lip = fv[basis.lip_landmarks]
    xl, xr = sorted((lip[12, 0], lip[16, 0]))  # the inner corners (landmarks 60, 64)
    xc, hw = 0.5 * (xl + xr), 0.5 * (xr - xl)
    op = np.asarray(opacities, np.float64).reshape(-1)
    sel = (op > 0.3) & (np.abs(q[:, 0] - xc) < LIP_SEAM_COLUMNS * hw) & (q[:, 2] > lip[:, 2].max() - LIP_SEAM_DEPTH)
    sel &= np.abs(q[:, 1] - ys) < LIP_SEAM_SEARCH + 3 * LIP_SEAM_SMOOTH
    if int(sel.sum()) < LIP_SEAM_MIN_POINTS:
        return 0.0
    luma = np.asarray(colors, np.float64)[sel] @ np.array([0.299, 0.587, 0.114])
    y = q[sel, 1] - ys
    bins = np.arange(-LIP_SEAM_SEARCH, LIP_SEAM_SEARCH + 1e-9, LIP_SEAM_SMOOTH / 3)
    k = np.exp(-0.5 * ((y[None] - bins[:, None]) / LIP_SEAM_SMOOTH) ** 2) * op[sel][None]  # [B, n]
    w = k.sum(1)
    ok = w > 0.5
    if not ok.any():
        return 0.0
    prof = (k @ luma)[ok] / w[ok]
    if float(prof.max() - prof.min()) < LIP_SEAM_MIN_CONTRAST:  # no darker lip to place it by
        return 0.0
    return float(np.clip(bins[ok][int(np.argmin(prof))] - LIP_SEAM_BELOW, -LIP_SEAM_MAX_SHIFT, LIP_SEAM_MAX_SHIFT))


@functools.lru_cache(maxsize=2)
def _flame_basis(path: str) -> HeadBasis:
    if path.endswith(".npz"):
        with np.load(path, allow_pickle=False) as d:
            data = {k: d[k] for k in d.files}
    else:
        import pickle

        with open(path, "rb") as fh:
            data = pickle.load(fh, encoding="latin1")  # noqa: S301 - a file the user chose to trust
    try:
        vt = np.asarray(data["v_template"], np.float32)
        sd = np.asarray(data["shapedirs"], np.float32)  # [Nv, 3, 300 + 100]
        f = np.asarray(data["f"], np.int64)
    except KeyError as e:
        raise ValueError(f"FLAME model file {path}: missing {e.args[0]!r} (expected v_template, shapedirs, f)") from None
    if sd.ndim != 3 or sd.shape[:2] != vt.shape or sd.shape[2] < 400:
        raise ValueError(f"FLAME model file {path}: shapedirs must be [Nv, 3, 400], got {list(sd.shape)}")
    # FLAME: metres, +y up, +z forward; centre it like the ICT model (midway chin-crown, back-nose).
    c = np.array([0.0, 0.5 * (vt[:, 1].min() + vt[:, 1].max()), 0.5 * (vt[:, 2].min() + vt[:, 2].max())], np.float32)
    ident = np.transpose(sd[:, :, :40], (2, 0, 1)).copy()
    expr = np.transpose(sd[:, :, 300:400], (2, 0, 1)).copy()
    expr = np.concatenate([expr, np.zeros((20, *vt.shape), np.float32)])  # jaw/eye rotations: MLP only
    front = np.flatnonzero(vt[:, 2] > np.percentile(vt[:, 2], 60))
    e0 = np.zeros(0, np.int64)
    return HeadBasis(
        "flame120", vt - c, ident, expr, f.astype(np.int32), front, e0, np.zeros((0, 3), np.float32), 0.002,
        np.zeros((1, 120), np.float32), np.array([[GATE_START, GATE_FULL]], np.float32), e0, np.zeros(0, np.float32), np.zeros(0, bool),
        np.zeros(len(vt), np.int8),
    )


# ---------------------------------------------------------------------------- fitting
@dataclass
class HeadFit:
    """A fitted head: ``world = transform[:3, :3] @ (neutral + identity @ basis) + transform[:3, 3]``."""

    identity: np.ndarray  # [K]
    transform: np.ndarray  # [4, 4]: scale * rotation | offset
    vertices: np.ndarray  # [Nv, 3] world
    rms: float  # RMS distance (metres) of the kept correspondences in the last iteration


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and offset t minimising ``|R src + t - dst|``."""
    cs, cd = src.mean(0), dst.mean(0)
    h = (src - cs).T @ (dst - cd)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


@functools.lru_cache(maxsize=2)
def _normals_cached(key: int, basis: HeadBasis) -> np.ndarray:
    from ..data.headmodel import vertex_normals

    return vertex_normals(basis.neutral, basis.bind_faces).astype(np.float64)


def _neutral_normals(basis: HeadBasis) -> np.ndarray:
    """``[Nv, 3]`` unit vertex normals of the generic neutral surface."""
    return _normals_cached(id(basis), basis)


def fit_head(points: np.ndarray, basis: HeadBasis, iters: int = 10, keep: float = 0.5, ridge: float = 4.0, free_scale: bool = False) -> HeadFit:
    """Fit identity modes and a rigid transform (a similarity with ``free_scale``) to a point cloud (trimmed ICP).

    Args:
        points: ``[P, 3]`` canonical Gaussian centres (metres, head roughly at the origin).
        basis: the head basis.
        iters: ICP iterations (each: correspondences, linear shape solve, rigid update).
        keep: fraction of correspondences kept (the closest), so hair and stray Gaussians do not pull
            (0.5: on held-out synthetic reconstructions the mean landmark error of the fit drops from
            5.3 mm at 0.8 to 4.2 mm).
        ridge: weight of the ``|identity|^2`` penalty (unit-variance modes), in mm^2 of point noise.
        free_scale: solve a global scale besides the identity modes. Off by default: the identity
            modes already carry the head's size, and a free scale trades off against them (it settled
            at 0.90-0.94 on held-out synthetic heads of the model's own size), which shrinks every
            blendshape displacement by the same factor, since the prior applies the fit's scale.
    Raises:
        ValueError: fewer than 100 points.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 100:
        raise ValueError(f"fit_head needs a point cloud [P >= 100, 3], got {list(p.shape)}")
    if len(p) > 10000:  # a spread subset is as good for the fit and keeps it fast
        p = p[np.linspace(0, len(p) - 1, 10000).astype(np.int64)]
    tree = cKDTree(p)
    ids = basis.fit_vertices
    if len(ids) > 1500:
        ids = ids[np.linspace(0, len(ids) - 1, 1500).astype(np.int64)]
    n0 = basis.neutral[ids].astype(np.float64)  # [M, 3]
    B = basis.identity_basis[:, ids].astype(np.float64)  # [K, M, 3]
    K = B.shape[0]
    nz = _neutral_normals(basis)[ids]  # [M, 3]
    R, off = np.eye(3), np.zeros(3)  # world = R local + off
    sc, a, tm = 1.0, np.zeros(K), np.zeros(3)  # local = sc * n0 + B a + tm (model frame)
    rms = float("nan")
    for it in range(iters):
        local = sc * n0 + np.tensordot(a, B, axes=1) + tm
        world = local @ R.T + off
        d, j = tree.query(world)
        m = d <= np.quantile(d, keep)
        rms = float(np.sqrt(np.mean(d[m] ** 2)))
        q = (p[j[m]] - off) @ R  # correspondences in the model frame
        # linear in (sc, a, tm): q ~ sc n0 + B a + tm, ridge on a (relative to sc)
        mm = int(m.sum())
        A = np.concatenate([n0[m].reshape(-1, 1), B[:, m].reshape(K, -1).T, np.tile(np.eye(3), (mm, 1))], axis=1)  # [3M', 1+K+3]
        rhs = q.reshape(-1)
        # point-to-plane rows (the model's normals; converge far faster than point-to-point alone,
        # which slides along the surface) + point-to-point rows at a small weight (well-posed)
        nrm = nz[m]  # [M', 3]
        Ap = (A.reshape(mm, 3, -1) * nrm[:, :, None]).sum(1)  # [M', 1+K+3]
        bp = (q * nrm).sum(1)
        A = np.concatenate([Ap, 0.3 * A])
        rhs = np.concatenate([bp, 0.3 * rhs])
        # MAP with unit-variance modes and ~2 mm point noise: ridge = noise variance (m^2)
        reg = np.diag(np.concatenate([[0.0], np.full(K, ridge * 1e-6), np.zeros(3)]))
        if free_scale:
            sol = np.linalg.solve(A.T @ A + reg + 1e-12 * np.eye(len(reg)), A.T @ rhs)
            sc = float(np.clip(sol[0], 0.8, 1.25))
        else:  # sc = 1: its column moves to the right-hand side
            rest = np.linalg.solve(A[:, 1:].T @ A[:, 1:] + reg[1:, 1:] + 1e-12 * np.eye(len(reg) - 1), A[:, 1:].T @ (rhs - A[:, 0]))
            sol = np.concatenate([[1.0], rest])
            sc = 1.0
        a, tm = sol[1 : 1 + K], sol[1 + K :]
        local = sc * n0[m] + np.tensordot(a, B[:, m], axes=1) + tm
        R, off = _kabsch(local, p[j[m]])
    # world = R (sc (n0 + B a / sc) + tm) + off
    s = sc
    a = a / sc
    off = off + R @ tm
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = off
    allv = basis.neutral.astype(np.float64) + np.tensordot(a.astype(np.float32), basis.identity_basis, axes=1)
    verts = allv @ T[:3, :3].T + T[:3, 3]
    return HeadFit(identity=a.astype(np.float32), transform=T.astype(np.float32), vertices=verts.astype(np.float32), rms=rms)


def generic_fit(basis: HeadBasis) -> HeadFit:
    """The generic neutral head at the origin (no identity, unit transform)."""
    k = basis.identity_basis.shape[0]
    return HeadFit(np.zeros(k, np.float32), np.eye(4, dtype=np.float32), basis.neutral.astype(np.float32), float("nan"))


# ---------------------------------------------------------------------------- binding
def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of ``p [..., 3]`` on triangles ``(a, b, c) [..., 3]`` (Ericson, Real-Time
    Collision Detection §5.1.5) -> ``(barycentric [..., 3], distance [...])``."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    eps = 1e-30
    # interior
    denom = va + vb + vc
    v = vb / np.where(np.abs(denom) > eps, denom, eps)
    w = vc / np.where(np.abs(denom) > eps, denom, eps)
    bary = np.stack([1 - v - w, v, w], -1)
    # regions, from the last assignment's lowest priority to the highest
    def put(mask, val):
        nonlocal bary
        bary = np.where(mask[..., None], val, bary)

    # edge BC
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    wbc = (d4 - d3) / np.maximum((d4 - d3) + (d5 - d6), eps)
    put(m, np.stack([np.zeros_like(wbc), 1 - wbc, wbc], -1))
    # edge AC
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    wac = d2 / np.maximum(d2 - d6, eps)
    put(m, np.stack([1 - wac, np.zeros_like(wac), wac], -1))
    # edge AB
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    vab = d1 / np.maximum(d1 - d3, eps)
    put(m, np.stack([1 - vab, vab, np.zeros_like(vab)], -1))
    one, zero = np.ones_like(d1), np.zeros_like(d1)
    put((d6 >= 0) & (d5 <= d6), np.stack([zero, zero, one], -1))  # vertex C
    put((d3 >= 0) & (d4 <= d3), np.stack([zero, one, zero], -1))  # vertex B
    put((d1 <= 0) & (d2 <= 0), np.stack([one, zero, zero], -1))  # vertex A
    q = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
    return bary, np.linalg.norm(p - q, axis=-1)


@dataclass
class PriorBinding:
    """Per-Gaussian binding to the fitted head surface.

    Attributes:
        vertex_ids: ``[N, 3]`` int64 head-model vertex ids (the nearest triangle's corners).
        bary: ``[N, 3]`` float32 barycentric coordinates of the nearest surface point.
        weight: ``[N]`` float32 fade weight in [0, 1] (1 on the surface, 0 far away).
        transform: ``[4, 4]`` float32, the fit's scale * rotation | offset.
        identity: ``[K]`` float32 fitted identity weights.
        space: expression space of the basis.
    """

    vertex_ids: Tensor
    bary: Tensor
    weight: Tensor
    transform: Tensor
    identity: Tensor
    space: str
    # [N] int64: gate group of interior Gaussians (0..G-1); reconstructed ones: -1, or a hide group
    # (G..2G-2: eyes under closing lids, ``bind``; 2G-1: open-mouthed photos' lips, ``hide_open_lips``)
    group: Tensor | None = None

    def __len__(self) -> int:
        return int(self.vertex_ids.shape[0])

    def groups(self) -> Tensor:
        """``[N]`` gate group per Gaussian (-1: none)."""
        return self.group if self.group is not None else torch.full((len(self),), -1, dtype=torch.int64, device=self.vertex_ids.device)

    def index(self, idx) -> "PriorBinding":
        return PriorBinding(self.vertex_ids[idx], self.bary[idx], self.weight[idx], self.transform, self.identity, self.space, self.groups()[idx])

    @staticmethod
    def concat(a: "PriorBinding", b: "PriorBinding") -> "PriorBinding":
        return PriorBinding(
            torch.cat([a.vertex_ids, b.vertex_ids]), torch.cat([a.bary, b.bary]), torch.cat([a.weight, b.weight]), a.transform, a.identity, a.space,
            torch.cat([a.groups(), b.groups().to(a.vertex_ids.device)]),
        )

    def tensors(self) -> dict[str, Tensor]:
        """Tensors for the avatar file (``prior.*``)."""
        return {
            "prior.vertex_ids": self.vertex_ids.to(torch.int32).contiguous(),
            "prior.bary": self.bary.float().contiguous(),
            "prior.weight": self.weight.float().contiguous(),
            "prior.transform": self.transform.float().contiguous(),
            "prior.identity": self.identity.float().contiguous(),
            "prior.group": self.groups().to(torch.int8).contiguous(),
        }

    @staticmethod
    def from_tensors(t: dict[str, Tensor], space: str, n: int) -> "PriorBinding | None":
        keys = ("prior.vertex_ids", "prior.bary", "prior.weight", "prior.transform", "prior.identity")
        if not all(k in t for k in keys):
            return None
        grp = t["prior.group"].long() if "prior.group" in t else None
        b = PriorBinding(t[keys[0]].long(), t[keys[1]].float(), t[keys[2]].float(), t[keys[3]].float(), t[keys[4]].float(), space, grp)
        if grp is not None and grp.shape != (n,):
            raise ValueError(f"avatar prior group must be [N={n}], got {list(grp.shape)}")
        if b.vertex_ids.shape != (n, 3) or b.bary.shape != (n, 3) or b.weight.shape != (n,):
            raise ValueError(f"avatar prior tensors must be [N={n}, 3], [N, 3], [N]; got {list(b.vertex_ids.shape)}, {list(b.bary.shape)}, {list(b.weight.shape)}")
        return b

    def fitted_vertices(self, basis: HeadBasis) -> np.ndarray:
        """``[Nv, 3]`` vertices of the fitted head surface in the avatar's frame (metres)."""
        T = self.transform.double().cpu().numpy()
        k = int(self.identity.shape[0])
        v = basis.neutral.astype(np.float64) + np.tensordot(self.identity.double().cpu().numpy(), basis.identity_basis[:k], axes=1)
        return (v @ T[:3, :3].T + T[:3, 3]).astype(np.float32)

    def to(self, device) -> "PriorBinding":
        return PriorBinding(
            *(x.to(device) for x in (self.vertex_ids, self.bary, self.weight, self.transform, self.identity)), self.space,
            None if self.group is None else self.group.to(device),
        )


def nearest_neighbours(data: np.ndarray, queries: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``cKDTree(data).query(queries, k)`` on every core: distances and indices, ``[N]`` for ``k`` 1,
    else ``[N, k]``.

    The queries are split into one chunk per core, each queried in a thread of our own that holds its
    own arrays. scipy's ``workers=-1`` runs threads over the caller's buffers, and a Ctrl-C arriving
    while the caller waited for them unwound the caller under the running threads: a segmentation
    fault in 5 of 6 interrupts of ``fastgha train`` (2026-12-06). Here an interrupt waits for the
    chunks (milliseconds) before it propagates.
    """
    from concurrent.futures import ThreadPoolExecutor

    from scipy.spatial import cKDTree

    tree = cKDTree(data)
    n = min(os.cpu_count() or 1, max(1, len(queries) // 4096))
    if n == 1:
        return tree.query(queries, k=k)
    with ThreadPoolExecutor(n) as pool:  # cKDTree.query releases the GIL
        parts = list(pool.map(lambda chunk: tree.query(chunk, k=k), np.array_split(queries, n)))
    return np.concatenate([d for d, _ in parts]), np.concatenate([i for _, i in parts])


def bind(points: np.ndarray | Tensor, fit: HeadFit, basis: HeadBasis, fade: tuple[float, float] = (0.006, 0.025), k: int = 4, hide_inside: bool = False) -> PriorBinding:
    """Bind ``points [N, 3]`` to their nearest triangle of the fitted surface (see module doc).

    ``hide_inside``: points nearer the fitted mouth interior than the skin fade out as the mouth opens
    (``_inside_mouth``; for avatars on a tracked head surface, whose photos' Gaussians lie on the
    tracked mesh).

    ``fade = (d0, d1)`` metres: full weight up to ``d0`` from the surface, none beyond ``d1``.
    The nearest triangle is searched among the ``k`` triangles with the nearest centroids, leaving out
    the mouth's inside (``basis.mouth_faces``: teeth, gums/tongue, socket). A reconstruction shows the
    outside of a closed mouth; its Gaussians sit a few mm off the fitted surface, and near the lips
    the socket and gums right behind them were often nearer than the lip skin (500-650 of ~33k
    Gaussians per held-out avatar). Bound there, they did not follow the lips: with ``mouthSmile``
    the lips moved back and out while those stayed, a pale or white crack under the lower lip.
    """
    p = points.detach().cpu().float().numpy() if isinstance(points, Tensor) else np.asarray(points, np.float32)
    f = basis.bind_faces if basis.mouth_faces is None else basis.bind_faces[~basis.mouth_faces]
    v = fit.vertices.astype(np.float32)
    cen = v[f].mean(1)  # [F, 3]
    k = min(k, len(f))
    _, cand = nearest_neighbours(cen, p, k=k)  # [N, k]
    cand = cand.reshape(len(p), k)
    tri = f[cand]  # [N, k, 3]
    bary, dist = _closest_on_triangles(p[:, None, :], v[tri[..., 0]], v[tri[..., 1]], v[tri[..., 2]])
    best = dist.argmin(1)
    r = np.arange(len(p))
    ids = tri[r, best]  # [N, 3]
    bc = bary[r, best]
    d = dist[r, best]
    d0, d1 = fade
    w = 1.0 - _smoothstep((d - d0) / max(d1 - d0, 1e-9))
    # gate group: -1, or G - 1 + k for Gaussians that fade out with gate k (eyes under closing lids)
    hg = basis.hide_group[ids[:, 0]].astype(np.int64)
    group = np.where((hg > 0) & (d < d1), basis.gates.shape[0] - 1 + hg, -1)
    if hide_inside:
        group[_inside_mouth(p, d, fit, basis) & (group < 0)] = lip_hide_group(basis)
    return PriorBinding(
        torch.from_numpy(ids.astype(np.int64)),
        torch.from_numpy(bc.astype(np.float32)),
        torch.from_numpy(w.astype(np.float32)),
        torch.from_numpy(fit.transform.astype(np.float32)),
        torch.from_numpy(fit.identity.astype(np.float32)),
        basis.space,
        torch.from_numpy(group),
    )


def _inside_mouth(points: np.ndarray, skin_dist: np.ndarray, fit: HeadFit, basis: HeadBasis) -> np.ndarray:
    """``[N]`` bool: ``points [N, 3]`` nearer the fitted head's mouth interior (the vertices only
    ``basis.mouth_faces`` use: teeth, gums/tongue, socket) than their distance ``skin_dist [N]`` to the
    nearest skin triangle (``bind``'s). All False without mouth faces.

    Why (issue 16, real photo sets): a photo that shows its teeth (studio-4's and phone-5's smiles)
    puts their pixels on the tracked head's mouth; undone to the neutral head they sit inside the
    closed mouth, unseen, but bound to the nearest skin (the lower lip, the mouth's corners) they
    moved into the opening with ``jawOpen``: beige blobs and pink patches over the avatar's own
    interior. ``bind(..., hide_inside=True)`` gives them ``lip_hide_group``: they fade out as the
    mouth opens. Only on a tracked head surface (``FastGHA.build_prior`` with ``head_fit``): on the
    network's depth the Gaussians inside the fitted mouth are the avatar's own lips and opening
    (450-750 per held-out synthetic subject, 7 mm median from the skin); hiding them cost 1.6 dB of
    the mouth's PSNR on jawOpen (draw B, 256²)."""
    if basis.mouth_faces is None or not basis.mouth_faces.any() or len(points) == 0:
        return np.zeros(len(points), bool)
    f = basis.bind_faces
    inner = np.setdiff1d(np.unique(f[basis.mouth_faces]), np.unique(f[~basis.mouth_faces]))
    if not len(inner):
        return np.zeros(len(points), bool)
    di, _ = nearest_neighbours(fit.vertices[inner].astype(np.float32), np.asarray(points))
    return di < skin_dist


def _lid_skin_colors(points: np.ndarray, M: np.ndarray, tree, colors: np.ndarray, k: int = 16) -> np.ndarray:
    """Skin colour ``[P, 3]`` for closed-eyelid points ``[P, 3]`` from an avatar's Gaussians
    (``tree``: a ``scipy.spatial.cKDTree`` of their centres, ``colors [N, 3]``; solid ones): the ``k`` nearest Gaussians to the lid crease (6 mm above
    each point) and to the skin under the eye (14 mm below), and of those 2k the median of the brighter
    half. Only skin is that bright there: eyebrows, lashes, the iris and a reconstruction's doubled
    dark eye all sit in those neighbourhoods and, with a plain median, made a closed lid look like dark
    glasses (issue 16, real photo sets). ``M [3, 3]``: the head fit's linear part (its up axis)."""
    up = M[:, 1] / max(np.linalg.norm(M[:, 1]), 1e-9)
    fwd = M[:, 2] / max(np.linalg.norm(M[:, 2]), 1e-9)
    _, above = tree.query(points + (0.006 * up + 0.002 * fwd).astype(np.float32), k=k)
    _, below = tree.query(points + (-0.014 * up + 0.004 * fwd).astype(np.float32), k=k)
    c = colors[np.concatenate([above, below], axis=1)]  # [P, 2k, 3]
    lum = c @ _LUMA  # [P, 2k]
    order = np.argsort(lum, axis=1)[:, k:]  # the brighter half
    return np.median(np.take_along_axis(c, order[..., None], axis=1), axis=1).astype(np.float32)


def _lash_color(lid: np.ndarray, tree, colors: np.ndarray, skin: np.ndarray, k: int = 8) -> np.ndarray:
    """The closed lashes' colour ``[3]`` of one eye, from the avatar.

    ``lid [P, 3]``: the part of that eye's upper lid that closes over the eye, where it sits with the
    eye open (its lash line); ``tree``: a ``scipy.spatial.cKDTree`` of the avatar's solid Gaussian
    centres with ``colors [N, 3]``; ``skin [3]``: the closed lid's colour. The colour is the median of
    the darkest quarter of the Gaussians among the ``k`` nearest to each lid point (the lashes and the
    lid margin of the open eye), scaled down to ``LASH_MAX_LUMA`` times the skin's luma when it is
    brighter than that (a blurred reconstruction can leave no dark lash line to take it from)."""
    _, nn = tree.query(lid, k=k)
    c = colors[np.unique(nn)]
    dark = c[np.argsort(c @ _LUMA)[: max(1, len(c) // 4)]]
    col = np.median(dark, axis=0)
    cap = LASH_MAX_LUMA * float(skin @ _LUMA)
    luma = float(col @ _LUMA)
    if luma > cap:
        col = col * (cap / max(luma, 1e-6))
    return np.clip(col, 0.0, 1.0).astype(np.float32)


# The closed lid's own Gaussians fade in over LID_EDGE_TRAVEL (metres of blink travel) from
# LID_EDGE_OPACITY (times LID_OPACITY) at the crease side to full: a soft edge, not a cut-out oval.
LID_EDGE_TRAVEL = (0.0025, 0.0045)
# The closed lid's backing: every LID_BACK_STEP-th upper-lid vertex once more, as a LID_BACK_SCALE
# (metres) Gaussian LID_BACK_INSET behind the lid along the fitted head's forward axis, coloured like
# the lid. A closing lid fades the reconstructed Gaussians bound to its eyeball; where the avatar's eye
# is wider or sits lower than the fitted one (1-5 mm on real photos), that left a hole around the
# lid through which the back shell's inside (the hair's dark brown) showed: a dark outline, "goggles".
LID_BACK_STEP = 2
LID_BACK_SCALE = 0.004
LID_BACK_INSET = 0.015
LID_EDGE_OPACITY = 0.3
LID_OPACITY = 0.9


def _lid_parts(basis: HeadBasis) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Per lid gate ``k``: ``(k, lid_rows, travel)``, the rows of ``basis.interior_vertices`` that are that
    eye's closed-lid skin (not lashes, not the backing) and how far (metres, head model units) its blink moves each."""
    ids, grp = basis.interior_vertices, basis.interior_group
    lash = np.zeros(len(ids), bool) if basis.lash is None else basis.lash
    if basis.lid_back is not None:
        lash = lash | basis.lid_back
    out = []
    for k in range(1, basis.gates.shape[0]):
        rows = np.flatnonzero((grp == k) & ~lash & basis.sample_color)
        if not len(rows):
            continue
        shapes = np.flatnonzero(basis.gates[k] > 0)
        travel = np.linalg.norm(basis.expression_basis[shapes][:, ids[rows]], axis=-1).max(0)
        out.append((k, rows, travel))
    return out


def interior_inset(points: np.ndarray | Tensor, fit: HeadFit, basis: HeadBasis, opacities: np.ndarray | Tensor | None = None) -> float:
    """How far (metres) to move the mouth interior back behind the fitted head's lips: as deep as the
    avatar's own lips are drawn behind the fitted lip surface.

    ``points [N, 3]``: the reconstructed Gaussians where they are drawn at the neutral expression
    (metres), ``opacities [N]`` (only those above 0.3 count; all without). For the solid ones within
    ``LIP_RADIUS`` (times the fit's scale) of the fitted head's lip landmarks, the signed distance to
    their nearest fitted skin vertex along its normal (negative: behind the surface); the inset is
    minus its 10th percentile, clipped to ``[0, INTERIOR_INSET_MAX]`` (times the fit's scale), 0 with
    fewer than ``INSET_MIN_POINTS`` such Gaussians or without lip landmarks.

    Why (issue 16): a few-view reconstruction draws the lips 1-2 mm (median) and 3-4 mm (10th
    percentile) behind the fitted surface on held-out synthetic heads, while the interior's gums and
    socket sit right behind that surface. With the jaw open they drew through the moved lower lip: a
    dark ragged band under the opening's lower edge that dlib took for the opening's inside, reading
    a smaller lip gap. Raises ``ValueError`` for ``points`` that are not ``[N, 3]``.
    """
    from scipy.spatial import cKDTree

    from ..data.headmodel import vertex_normals

    p = points.detach().cpu().float().numpy() if isinstance(points, Tensor) else np.asarray(points, np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"interior_inset: points must be [N, 3], got {list(p.shape)}")
    if basis.lip_landmarks is None or len(p) == 0:
        return 0.0
    if opacities is not None:
        op = opacities.detach().cpu().numpy() if isinstance(opacities, Tensor) else np.asarray(opacities)
        p = p[op.reshape(-1) > 0.3]
    s = float(np.cbrt(abs(np.linalg.det(fit.transform[:3, :3].astype(np.float64)))))
    v = fit.vertices.astype(np.float64)
    near = cKDTree(v[basis.lip_landmarks]).query(p)[0] < LIP_RADIUS * s
    if int(near.sum()) < INSET_MIN_POINTS:
        return 0.0
    faces = basis.bind_faces if basis.mouth_faces is None else basis.bind_faces[~basis.mouth_faces]
    skin = np.unique(faces)
    nrm = vertex_normals(v, basis.bind_faces)[skin]
    q = p[near].astype(np.float64)
    _, j = cKDTree(v[skin]).query(q)
    signed = ((q - v[skin][j]) * nrm[j]).sum(1)
    return float(np.clip(-np.percentile(signed, 10), 0.0, INTERIOR_INSET_MAX * s))


def mouth_interior(
    fit: HeadFit, basis: HeadBasis, num_features: int, avatar: "Gaussians | None" = None, inset: float = 0.0, drawn: np.ndarray | Tensor | None = None  # noqa: F821
) -> tuple["Gaussians", PriorBinding]:  # noqa: F821
    """Gated Gaussians of the fitted head, each bound to its own vertex with full weight: the mouth
    interior (teeth, gums/tongue, mouth socket; coloured as the synthetic renderer shows them,
    ``INTERIOR_SHADE``; moved ``inset`` metres back along the fitted head's forward axis, see
    ``interior_inset``), the closed upper eyelids (coloured like the avatar's skin around the eye,
    ``_lid_skin_colors``; skin grey without ``avatar``; fading in towards the crease,
    ``LID_EDGE_*``; with a backing of wider Gaussians behind them, ``LID_BACK_*``) and their lashes (``_lash_color``;
    ``LASH_DEFAULT`` without ``avatar``), and the lip seam (``LIP_SEAM_NY``; ``lip_hide_group``: it
    fades as the mouth opens; flat across the seam and stretched along it, ``LIP_SEAM_AXES`` turned with the
    fit), coloured like the avatar's lips nearby times its brightness factor (``LIP_SEAM_DEFAULT``
    without ``avatar``) and moved along the fit's up axis to where the avatar's colours put the lip
    contact line (``_seam_shift``; with ``avatar``: at ``drawn [len(avatar), 3]``, where its Gaussians
    are drawn at the neutral expression, default their centres). ``features`` are zeros
    ``[I, num_features]``; the binding's ``group`` says which gate (``gate_factors``) hides each one."""
    from scipy.spatial import cKDTree

    from ..gaussians import Gaussians

    ids = basis.interior_vertices
    n = len(ids)
    M = fit.transform[:3, :3].astype(np.float64)
    s = float(np.cbrt(abs(np.linalg.det(M))))
    pos = fit.vertices[ids].astype(np.float32)
    fwd = M[:, 2] / max(np.linalg.norm(M[:, 2]), 1e-9)
    if inset:
        pos[basis.interior_group == 0] -= (float(inset) * fwd).astype(np.float32)
    cols = basis.interior_colors.astype(np.float32).copy()
    seam = np.zeros(n, bool) if basis.seam is None else basis.seam
    if seam.any():
        lip = np.array(LIP_SEAM_DEFAULT, np.float32)[None].repeat(int(seam.sum()), 0)
        if avatar is not None and len(avatar) > 0:
            op = avatar.opacities.detach().cpu().numpy() > 0.3
            if op.sum() >= LIP_SEAM_K:
                _, nn = cKDTree(avatar.means.detach().float().cpu().numpy()[op]).query(pos[seam], k=LIP_SEAM_K)
                lip = np.median(avatar.colors.detach().float().cpu().numpy()[op][nn], axis=1)
        cols[seam] = lip * cols[seam]
        if avatar is not None and len(avatar) > 0:
            pts = avatar.means if drawn is None else drawn
            pts = pts.detach().float().cpu().numpy() if isinstance(pts, Tensor) else np.asarray(pts)
            if pts.shape != (len(avatar), 3):
                raise ValueError(f"mouth_interior: drawn must have shape [{len(avatar)}, 3], got {list(pts.shape)}")
            rot, _ = _fit_frame(fit)
            up = rot[:, 1] * s
            shift = _seam_shift(fit, basis, pts, avatar.colors.detach().float().cpu().numpy(), avatar.opacities.detach().float().cpu().numpy())
            pos[seam] += (shift * up).astype(np.float32)
    lash = np.zeros(n, bool) if basis.lash is None else basis.lash
    smp = basis.sample_color & ~lash
    cols[lash] = np.array(LASH_DEFAULT, np.float32)
    if smp.any():
        cols[smp] = np.array([0.62, 0.48, 0.42], np.float32)
        if avatar is not None and len(avatar) > 0:
            am = avatar.means.detach().float().cpu().numpy()
            solid = avatar.opacities.detach().cpu().numpy() > 0.3
            if solid.sum() >= 16:
                ac = avatar.colors.detach().float().cpu().numpy()[solid]
                # every lid point takes the skin around the eye (``_lid_skin_colors``). Taking the
                # avatar's colour where the lid sits with the eye open (tried for the part that travels
                # <= 6 mm, 119 of 184 points an eye) gave that part the blurred lash line, crease shadow
                # and eye outline that a few-view reconstruction puts there: a closed lid darker than
                # the cheeks (luma 0.34-0.42 against 0.45-0.63 on the real sets), an oval dlib took for
                # an open eye (real-set EAR ratios 0.50 / 0.68 / 0.70 -> 0.48 / 0.53 / 0.60, issue 16).
                blink = np.flatnonzero(basis.gates[1:].sum(0) > 0)  # the lid gates' shapes (eyeBlink_L/R)
                travel = np.linalg.norm(basis.expression_basis[blink][:, ids[smp]], axis=-1).max(0) if len(blink) else np.zeros(int(smp.sum()))
                over_eye = travel > 0.006  # the part that closes over the eye: its open position is the lash line
                tree = cKDTree(am[solid])
                cols[smp] = _lid_skin_colors(pos[smp], M, tree, ac)
                grp = basis.interior_group
                for gi in np.unique(grp[lash]):  # each eye's lashes: dark colours at its open upper lid
                    sel = np.flatnonzero(smp)[over_eye & (grp[smp] == gi)]
                    if len(sel):
                        cols[lash & (grp == gi)] = _lash_color(pos[sel], tree, ac, np.median(cols[sel], axis=0))
    if basis.lid_back is not None:  # the closed lids' backing (coloured like the lid above), behind them
        pos[basis.lid_back] -= (LID_BACK_INSET * s * fwd).astype(np.float32)
    opac = np.full(n, LID_OPACITY, np.float32)
    for _, rows, travel in _lid_parts(basis):  # the closed lid's soft edge towards the crease
        t0, t1 = LID_EDGE_TRAVEL
        opac[rows] = LID_OPACITY * (LID_EDGE_OPACITY + (1.0 - LID_EDGE_OPACITY) * _smoothstep(np.clip((travel - t0) / (t1 - t0), 0.0, 1.0)))
    quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1))
    scales = np.repeat((basis.interior_scale * s).astype(np.float32)[:, None], 3, 1)
    if seam.any():  # flat across the seam, along it in the head's x (LIP_SEAM_AXES), turned with the fit
        from scipy.spatial.transform import Rotation

        rot, _ = _fit_frame(fit)
        x, y, z, w = Rotation.from_matrix(rot).as_quat()
        quats[seam] = np.array([w, x, y, z], np.float32)
        scales[seam] = (np.asarray(LIP_SEAM_AXES, np.float64) * s).astype(np.float32)
    g = Gaussians(
        means=torch.from_numpy(pos),
        quats=torch.from_numpy(quats),
        scales=torch.from_numpy(scales),
        opacities=torch.from_numpy(opac),
        colors=torch.from_numpy(np.clip(cols, 0, 1)),
        features=torch.zeros(n, num_features),
    )
    vid = torch.from_numpy(ids.astype(np.int64))[:, None].expand(n, 3).contiguous()
    bary = torch.tensor([1.0, 0.0, 0.0]).expand(n, 3).contiguous()
    b = PriorBinding(
        vid, bary, torch.ones(n), torch.from_numpy(fit.transform), torch.from_numpy(fit.identity), basis.space,
        torch.from_numpy(basis.interior_group.astype(np.int64)),
    )
    return g, b


# ---------------------------------------------------------------------------- back of the head
# Back-of-head shell (issue 17): Gaussians exist only on input pixels and no input sees the back of
# the head, so from behind an avatar was hollow and showed its face from inside. The shell puts flat
# Gaussians on the fitted head's skin behind the ears and above the hairline, subsampled to points
# BACK_SHELL_SPACING apart, BACK_SHELL_INSET inside the surface (behind what the inputs do see),
# BACK_SHELL_SCALE wide (tangential) and BACK_SHELL_SCALE * BACK_SHELL_FLAT thick (along the normal).
BACK_SHELL_SPACING = 0.0065  # metres: the least distance between shell points (883 points)
BACK_SHELL_INSET = 0.005  # metres inside the fitted surface
BACK_SHELL_SCALE = 0.0055  # metres, tangential scale (closes the gaps between points 6.5-13 mm apart)
BACK_SHELL_FLAT = 0.35  # normal scale / tangential scale
BACK_SHELL_OPACITY = 0.95
BACK_SHELL_RADIUS = 0.02  # metres: reconstructed Gaussians this near a shell point colour it
BACK_SHELL_DEFAULT = (0.16, 0.11, 0.08)  # dark brown, without an avatar to take a colour from
BACK_SHELL_EAR_CENTRE = np.array([0.08, -0.005, -0.022])  # metres, the neutral ICT head's (left) ear
BACK_SHELL_EAR = 0.04  # metres: no shell this near an ear


def _spaced(v: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``ids [K]`` vertex ids thinned so no two of ``v [Nv, 3]`` (metres) lie within ``BACK_SHELL_SPACING``:
    greedy Poisson-disc subsampling (keep a vertex when no kept one is that near), so every vertex of
    ``ids`` lies within that of a kept one (a voxel grid left 1 cm holes at its seams). ``[S]`` int64."""
    from scipy.spatial import cKDTree

    near = cKDTree(v[ids]).query_ball_point(v[ids], r=BACK_SHELL_SPACING)
    free = np.ones(len(ids), bool)
    keep = []
    for i in range(len(ids)):
        if free[i]:
            keep.append(i)
            free[near[i]] = False
    return ids[np.array(keep, np.int64)].astype(np.int64)


def _head_skin(basis: HeadBasis) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(v [Nv, 3], lm [68, 3], idx [S], p [S, 3])``: the neutral ICT-FaceKit vertices, its 68
    landmarks, the head skin's vertex ids (``HEAD_VERTEX_RANGE``) and their positions (metres)."""
    from ..data.headmodel import HEAD_VERTEX_RANGE, HeadModel

    v = basis.neutral
    idx = np.arange(HEAD_VERTEX_RANGE[0], HEAD_VERTEX_RANGE[1])
    return v, v[HeadModel.load().landmarks68], idx, v[idx]


def _away_from_ears(p: np.ndarray) -> np.ndarray:
    """``[S]`` bool: the points ``p [S, 3]`` (neutral head, metres) farther than ``BACK_SHELL_EAR`` from both ears."""
    side = np.c_[np.abs(p[:, 0]), p[:, 1:]]  # both ears on the +x side
    return np.linalg.norm(side - BACK_SHELL_EAR_CENTRE, axis=1) > BACK_SHELL_EAR


@functools.lru_cache(maxsize=2)
def _back_shell_cached(key: int, basis: HeadBasis) -> np.ndarray:
    v, lm, idx, p = _head_skin(basis)
    brow = lm[17:27, 1].max()
    # behind the ears (down to the chin's height: the back of the neck too) or above the hairline
    sel = ((p[:, 2] < lm[0, 2] - 0.02) & (p[:, 1] > lm[8, 1] - 0.02)) | (p[:, 1] > brow + 0.045)
    # not the skin within BACK_SHELL_EAR of the ears: seen from the side, a shell there showed through
    # the reconstructed ear as a dark rim (held-out PSNR 20.56 -> 20.49 dB on synth_1000001)
    sel &= _away_from_ears(p)
    return _spaced(v, idx[sel])


def back_shell_vertices(basis: HeadBasis) -> np.ndarray:
    """``[S]`` int64 vertex ids of the back-of-head shell: ICT-FaceKit head skin behind the ears and
    above the hairline, no two closer than ``BACK_SHELL_SPACING`` on the neutral head.
    Empty for other head models (their vertex layout is not known here)."""
    if basis.space != "ict53":
        return np.zeros(0, np.int64)
    return _back_shell_cached(id(basis), basis)


def _quat_z_to(n: np.ndarray) -> np.ndarray:
    """``[P, 4]`` unit quaternions (w, x, y, z) rotating +z onto the unit vectors ``n [P, 3]``."""
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], -1)
    flip = q[:, 0] < 1e-6  # n = -z: half a turn about x
    q[flip] = np.array([0.0, 1.0, 0.0, 0.0])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def back_shell(fit: HeadFit, basis: HeadBasis, num_features: int, avatar: "Gaussians | None" = None, ids: np.ndarray | None = None) -> tuple["Gaussians", PriorBinding]:  # noqa: F821
    """Ungated Gaussians on the back of the fitted head (``back_shell_vertices``), an opaque skin the
    reconstruction has no pixels for.

    Each is a flat disc (``BACK_SHELL_SCALE`` wide, ``BACK_SHELL_FLAT`` as thick) tangent to the fitted
    surface, ``BACK_SHELL_INSET`` inside it. Colour: the median of the solid (opacity > 0.3) avatar
    Gaussians within ``BACK_SHELL_RADIUS`` of its surface point when there are at least 4; a point
    with fewer takes the colour of the nearest point that has them (the hair or skin at the edge of
    what the inputs saw); ``BACK_SHELL_DEFAULT`` when no point has any. Bound with weight 0 and no
    gate group: they move with the head only (the skull does not take expressions).
    ``ids``: other vertex ids to lay the discs on (``chin_shell``); default ``back_shell_vertices``.
    Returns ``(gaussians [S], binding [S])``; ``features`` are zeros ``[S, num_features]``.
    """
    from scipy.spatial import cKDTree

    from ..data.headmodel import vertex_normals
    from ..gaussians import Gaussians

    ids = back_shell_vertices(basis) if ids is None else ids
    n = len(ids)
    M = fit.transform[:3, :3].astype(np.float64)
    s = float(np.cbrt(abs(np.linalg.det(M))))
    nrm = vertex_normals(fit.vertices, basis.bind_faces).astype(np.float64)[ids]
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
    surf = fit.vertices[ids].astype(np.float64)
    pos = (surf - BACK_SHELL_INSET * s * nrm).astype(np.float32)
    cols = np.tile(np.array(BACK_SHELL_DEFAULT, np.float32), (n, 1))
    if avatar is not None and len(avatar) > 0 and n:
        am = avatar.means.detach().float().cpu().numpy()
        solid = avatar.opacities.detach().cpu().numpy() > 0.3
        if solid.sum() >= 16:
            ac = avatar.colors.detach().float().cpu().numpy()[solid]
            near = cKDTree(am[solid]).query_ball_point(surf, r=BACK_SHELL_RADIUS * s)
            have = np.array([len(x) >= 4 for x in near], bool)
            if have.any():
                cols[have] = np.stack([np.median(ac[x], axis=0) for x, h in zip(near, have) if h])
                if (~have).any():
                    _, j = cKDTree(surf[have]).query(surf[~have])
                    cols[~have] = cols[have][j]
    sc = np.array([1.0, 1.0, BACK_SHELL_FLAT], np.float32) * (BACK_SHELL_SCALE * s)
    g = Gaussians(
        means=torch.from_numpy(pos),
        quats=torch.from_numpy(_quat_z_to(nrm).astype(np.float32)),
        scales=torch.from_numpy(sc)[None].expand(n, 3).contiguous(),
        opacities=torch.full((n,), BACK_SHELL_OPACITY),
        colors=torch.from_numpy(np.clip(cols, 0, 1).astype(np.float32)),
        features=torch.zeros(n, num_features),
    )
    b = PriorBinding(
        torch.from_numpy(ids)[:, None].expand(n, 3).contiguous(), torch.tensor([1.0, 0.0, 0.0]).expand(n, 3).contiguous(), torch.zeros(n),
        torch.from_numpy(fit.transform), torch.from_numpy(fit.identity), basis.space, torch.full((n,), -1, dtype=torch.int64),
    )
    return g, b


# Chin shell: the back shell's kind of opaque skin under the jaw and on the front of the neck. A
# pitched-up render looks at the jaw's underside, which no less pitched input sees: the face's
# Gaussians left gaps there and the back shell showed through them as a dark hatched patch.
CHIN_SHELL_DOWN = -0.3  # the jaw's underside: neutral vertex normals with y below this (facing down)
CHIN_SHELL_FRONT = 0.02  # metres behind the jaw's corner (landmark 0): the back shell's bound
CHIN_SHELL_TOP = 0.012  # metres above the chin's lowest point (landmark 8): the shell's top (0.032, up to the lower lip: phone-5's jawOpen gap 0.263 -> 0.236)


@functools.lru_cache(maxsize=2)
def _chin_shell_cached(key: int, basis: HeadBasis) -> np.ndarray:
    from ..data.headmodel import vertex_normals

    v, lm, idx, p = _head_skin(basis)
    ny = vertex_normals(v, basis.bind_faces)[idx, 1]
    # in front of the back shell, below the lower lip: the jaw's underside, or the neck under the chin
    sel = (p[:, 2] >= lm[0, 2] - CHIN_SHELL_FRONT) & (p[:, 1] < min(lm[57, 1], lm[8, 1] + CHIN_SHELL_TOP)) & ((ny < CHIN_SHELL_DOWN) | (p[:, 1] < lm[8, 1]))
    return _spaced(v, idx[sel])


def chin_shell_vertices(basis: HeadBasis) -> np.ndarray:
    """``[S]`` int64 vertex ids of the chin shell: ICT-FaceKit head skin below the lower lip (landmark
    57) and in front of the back shell (``CHIN_SHELL_FRONT`` behind landmark 0) that faces down
    (neutral normal y < ``CHIN_SHELL_DOWN``) or lies below the chin (landmark 8), no two closer than
    ``BACK_SHELL_SPACING`` on the neutral head. Empty for other head models."""
    if basis.space != "ict53":
        return np.zeros(0, np.int64)
    return _chin_shell_cached(id(basis), basis)


def chin_shell(fit: HeadFit, basis: HeadBasis, num_features: int, avatar: "Gaussians | None" = None) -> tuple["Gaussians", PriorBinding]:  # noqa: F821
    """Ungated Gaussians under the jaw and on the front of the neck (``chin_shell_vertices``): the
    back shell's discs (``back_shell``: size, inset, opacity, colour from nearby solid avatar
    Gaussians) on that skin, but bound with weight 1 to their vertex, so they follow the expression
    prior's displacement there (the jaw's underside moves with jawOpen).
    Returns ``(gaussians [S], binding [S])``."""
    g, b = back_shell(fit, basis, num_features, avatar=avatar, ids=chin_shell_vertices(basis))
    return g, PriorBinding(b.vertex_ids, b.bary, torch.ones(len(b)), b.transform, b.identity, b.space, b.group)


# Cheek shell: the same kind of opaque skin under the cheeks beside the mouth. Seen from a side, the
# line of sight through a cheek ends on the mouth interior (teeth, gums, socket; drawn whenever the lips
# part). Where refinement has thinned the reconstructed cheek (alpha 0.998 -> 0.93, 35 % of its pixels
# under 0.9 in the demo's turned frames), the socket's red showed through as dots on the cheek.
CHEEK_SHELL_TOP = 0.01  # metres above the nose's base (landmark 33): the shell's top, above the upper gums
CHEEK_SHELL_LIP = 0.01  # metres: no shell this near a lip landmark (48-67), so the opening stays open
CHEEK_SHELL_INNER = 0.005  # metres: the shell's inner edge, this far inside the mouth corners (landmarks 48, 54)


@functools.lru_cache(maxsize=2)
def _cheek_shell_cached(key: int, basis: HeadBasis) -> np.ndarray:
    v, lm, idx, p = _head_skin(basis)
    chin = np.zeros(len(v), bool)
    chin[_chin_shell_cached(key, basis)] = True
    # in front of the back shell, from the chin shell's top up to above the upper gums
    sel = (p[:, 2] >= lm[0, 2] - CHIN_SHELL_FRONT) & (p[:, 1] >= lm[8, 1] + CHIN_SHELL_TOP) & (p[:, 1] <= lm[33, 1] + CHEEK_SHELL_TOP)
    lips = lm[48:68]
    sel &= np.linalg.norm(p[:, None, :] - lips[None], axis=-1).min(1) > CHEEK_SHELL_LIP
    # beside the mouth only: in front of the teeth (philtrum, chin) the face is opaque from every view
    sel &= np.abs(p[:, 0]) >= np.abs(lm[[48, 54], 0]).min() - CHEEK_SHELL_INNER
    sel &= _away_from_ears(p)
    return _spaced(v, idx[sel & ~chin[idx]])


def cheek_shell_vertices(basis: HeadBasis) -> np.ndarray:
    """``[S]`` int64 vertex ids of the cheek shell: ICT-FaceKit head skin in front of the back shell
    (``CHIN_SHELL_FRONT`` behind landmark 0), from the chin shell's top (``CHIN_SHELL_TOP`` above
    landmark 8) up to ``CHEEK_SHELL_TOP`` above the nose's base (landmark 33), farther than
    ``CHEEK_SHELL_LIP`` from every lip landmark (48-67) and than ``BACK_SHELL_EAR`` from the ears,
    not in the chin shell, no two closer than ``BACK_SHELL_SPACING`` on the neutral head. Empty for
    other head models."""
    if basis.space != "ict53":
        return np.zeros(0, np.int64)
    return _cheek_shell_cached(id(basis), basis)


def cheek_shell(fit: HeadFit, basis: HeadBasis, num_features: int, avatar: "Gaussians | None" = None) -> tuple["Gaussians", PriorBinding]:  # noqa: F821
    """Ungated Gaussians under the skin of the cheeks and around the mouth (``cheek_shell_vertices``),
    made and bound as ``chin_shell``'s (weight 1: they follow the cheeks' expression displacement), so
    that a thinned cheek shows skin, not the mouth interior behind it. Returns ``(gaussians [S],
    binding [S])``."""
    g, b = back_shell(fit, basis, num_features, avatar=avatar, ids=cheek_shell_vertices(basis))
    return g, PriorBinding(b.vertex_ids, b.bary, torch.ones(len(b)), b.transform, b.identity, b.space, b.group)


# Face shell: the same kind of opaque skin under the face. A frontal render of an avatar built from
# turned photos (the frontal one left out) draws the forehead, brows and nose from pixels those photos
# saw at an angle: their pixel-sized Gaussians stand apart seen from in front, and the back shell, dark
# with the hair's colour, showed through the gaps as a hatched patch on the forehead and down the nose
# (docs/model-card-log.md, "A shell under the face"). Its discs take the colour of the skin around them,
# so a gap shows skin.
FACE_SHELL_EYE = 0.006  # metres: no shell this near an eye landmark (36-47), so the eyes stay the photos'
FACE_SHELL_BROW = 0.005  # metres above the brows' highest landmark (17-26): the forehead region's lower bound
FACE_SHELL_TOP = 0.045  # metres above the brows' highest landmark: the back shell's lower bound on the forehead


@functools.lru_cache(maxsize=4)
def _face_shell_cached(key: int, basis: HeadBasis, region: str) -> np.ndarray:
    v, lm, idx, p = _head_skin(basis)
    brow = lm[17:27, 1].max()
    low = brow + FACE_SHELL_BROW if region == "forehead" else lm[33, 1] + CHEEK_SHELL_TOP
    # in front of the back shell, up to where the back shell begins on the forehead
    sel = (p[:, 2] >= lm[0, 2] - CHIN_SHELL_FRONT) & (p[:, 1] > low) & (p[:, 1] <= brow + FACE_SHELL_TOP)
    sel &= np.linalg.norm(p[:, None, :] - lm[None, 36:48], axis=-1).min(1) > FACE_SHELL_EYE
    sel &= _away_from_ears(p)
    return _spaced(v, idx[sel])


def face_shell_vertices(basis: HeadBasis, region: str = "forehead") -> np.ndarray:
    """``[S]`` int64 vertex ids of the face shell: ICT-FaceKit head skin in front of the back shell
    (``CHIN_SHELL_FRONT`` behind landmark 0), up to ``FACE_SHELL_TOP`` above the brows (landmarks
    17-26), from ``FACE_SHELL_BROW`` above them (``region="forehead"``) or from the cheek shell's top
    (``CHEEK_SHELL_TOP`` above the nose's base, landmark 33: ``"upper"``, the nose, cheekbones and
    brows too), farther than ``FACE_SHELL_EYE`` from every eye landmark (36-47) and than
    ``BACK_SHELL_EAR`` from the ears, no two closer than ``BACK_SHELL_SPACING`` on the neutral head.
    Empty for ``"off"`` and for other head models. Raises ValueError for another region."""
    if region not in ("off", "forehead", "upper"):
        raise ValueError(f"face shell region must be off, forehead or upper, got {region!r}")
    if basis.space != "ict53" or region == "off":
        return np.zeros(0, np.int64)
    return _face_shell_cached(id(basis), basis, region)


def face_shell(fit: HeadFit, basis: HeadBasis, num_features: int, avatar: "Gaussians | None" = None, region: str = "forehead") -> tuple["Gaussians", PriorBinding]:  # noqa: F821
    """Ungated Gaussians under the face (``face_shell_vertices(basis, region)``), made and bound as
    ``chin_shell``'s (colour from the solid avatar Gaussians within ``BACK_SHELL_RADIUS``; weight 1:
    they follow the expression prior's displacement, the brows' raise included), so that gaps between
    the reconstructed Gaussians show skin, not the back of the head. Returns ``(gaussians [S],
    binding [S])``."""
    g, b = back_shell(fit, basis, num_features, avatar=avatar, ids=face_shell_vertices(basis, region))
    return g, PriorBinding(b.vertex_ids, b.bary, torch.ones(len(b)), b.transform, b.identity, b.space, b.group)


def mouth_gate_vector(basis: HeadBasis) -> Tensor:
    """``[E]`` weights whose dot product with an expression measures how far the lips are open."""
    return torch.from_numpy(basis.gate)


def open_mouth_views(view_expressions: np.ndarray | Tensor, basis: HeadBasis) -> np.ndarray:
    """``[V]`` bool: input views whose expression ``view_expressions [V, E]`` opens the mouth gate
    (``basis.gates[0] @ z``) above ``OPEN_VIEW_GATE``, except the view with the lowest gate, which is
    never marked (some view always keeps its lips). Raises ``ValueError`` for another shape."""
    ve = np.asarray(view_expressions.detach().cpu() if isinstance(view_expressions, Tensor) else view_expressions, np.float64)
    if ve.ndim != 2 or ve.shape[1] != basis.num_expression:
        raise ValueError(f"open_mouth_views: expected view expressions [V, {basis.num_expression}], got {list(ve.shape)}")
    gv = ve @ basis.gates[0].astype(np.float64)
    out = gv > OPEN_VIEW_GATE
    if len(gv):
        out[int(np.argmin(gv))] = False
    return out


def lip_hide_group(basis: HeadBasis) -> int:
    """The binding group of reconstructed Gaussians that fade out as the mouth opens
    (``1 - gate 0``; its slot is the last of ``factor_table``)."""
    return 2 * int(basis.gates.shape[0]) - 1


def hide_open_lips(binding: PriorBinding, points: np.ndarray | Tensor, view_index: Tensor, open_views: np.ndarray, basis: HeadBasis) -> PriorBinding:
    """Make the lip Gaussians of open-mouthed input views fade out as the avatar's mouth opens.

    Cause (issue 16, real photo sets): each photo's Gaussians sit on the tracked head at that photo's
    expression and are moved back by it to the neutral canonical head. Where a photo shows its mouth
    open or a broad smile, the tracked lips miss the photo's by a few mm: pixels of its teeth, of the
    dark gap and of the inner lip edges land on the tracked lips and, undone, sit on the closed neutral
    lips (hidden there behind the other views' lips). With ``jawOpen`` they travel with the lips and
    line the opening: a pale band over the lower lip and a lower upper-lip edge, which dlib takes for
    the inner lips (studio-4's lip-gap change +0.18 where its lower lip moves 0.41 interocular
    distances on screen). Gaussians of such views (``open_views [V]``, ``open_mouth_views``) within
    ``LIP_RADIUS`` (times the fit's scale) of the fitted head's lip landmarks, with weight > 0 and no
    gate group, get ``lip_hide_group``: at the neutral expression they draw as before, and the mouth's
    opening shows the lips of the closed-mouthed views and the avatar's own interior.

    Args:
        binding: the reconstructed Gaussians' binding (``N``).
        points: ``[N, 3]`` their neutral positions (those ``binding`` was made from; metres).
        view_index: ``[N]`` input view of each Gaussian.
        open_views: ``[V]`` bool.
        basis: the head basis (without ``lip_landmarks`` the binding is returned unchanged).
    Raises:
        ValueError: ``points`` or ``view_index`` not ``[N, 3]`` / ``[N]``.
    """
    from scipy.spatial import cKDTree

    p = points.detach().cpu().float().numpy() if isinstance(points, Tensor) else np.asarray(points, np.float32)
    if view_index.shape != (len(binding),) or p.shape != (len(binding), 3):
        raise ValueError(f"hide_open_lips: points and view_index must have shapes [{len(binding)}, 3] and [{len(binding)}], got {list(p.shape)} and {list(view_index.shape)}")
    if basis.lip_landmarks is None or not np.asarray(open_views).any():
        return binding
    vi = view_index.detach().cpu().long().numpy()
    ov = np.asarray(open_views, bool)
    scale = float(np.cbrt(abs(np.linalg.det(binding.transform[:3, :3].double().cpu().numpy()))))
    d, _ = cKDTree(binding.fitted_vertices(basis)[basis.lip_landmarks]).query(p)
    lip = d < LIP_RADIUS * scale
    grp = binding.groups().cpu().numpy().copy()
    sel = ov[vi] & lip & (binding.weight.cpu().numpy() > 0) & (grp < 0)
    grp[sel] = lip_hide_group(basis)
    return PriorBinding(
        binding.vertex_ids, binding.bary, binding.weight, binding.transform, binding.identity, binding.space,
        torch.from_numpy(grp).to(binding.vertex_ids.device),
    )


def mouth_gate(z: Tensor, gate: Tensor) -> Tensor:
    """Opacity factor of the mouth interior for ``z [E]`` or ``[B, E]`` -> ``[]`` / ``[B]`` in [0, 1]."""
    x = ((z @ gate) - GATE_START) / (GATE_FULL - GATE_START)
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def opacity_factors(z: Tensor, basis: HeadBasis, index: Tensor) -> Tensor:
    """Per-Gaussian opacity factors ``[N]`` (``[B, N]``) for ``z [E]`` (``[B, E]``); ``index [N]`` =
    ``binding.groups() + 1``. Slot 0 = 1 (no gate), slots 1..G = the gates (interior Gaussians appear),
    slots G+1..2G-1 = 1 - gate k (reconstructed Gaussians that hide, k = 1..G-1: eyes under the
    lids), slot 2G = 1 - gate 0 (open-mouthed views' lips, ``hide_open_lips``)."""
    gates = torch.as_tensor(basis.gates, device=z.device, dtype=z.dtype)
    return factor_table(z, gates, torch.as_tensor(basis.gate_ranges, device=z.device, dtype=z.dtype))[..., index]


def factor_table(z: Tensor, gates: Tensor, ranges: Tensor) -> Tensor:
    """The opacity factor of each slot of ``opacity_factors``: ``z [E]`` (``[B, E]``) -> ``[2G + 1]`` (``[B, 2G + 1]``)."""
    f = gate_factors(z, gates, ranges)
    one = torch.ones_like(f[..., :1])
    return torch.cat([one, f, 1.0 - f[..., 1:], 1.0 - f[..., :1]], dim=-1)  # [1 + G + (G - 1) + 1]


def gate_factors(z: Tensor, gates: Tensor, ranges: Tensor) -> Tensor:
    """Opacity factor per gate group: ``z [E]`` / ``[B, E]``, ``gates [G, E]``, ``ranges [G, 2]`` ->
    ``[G]`` / ``[B, G]`` = smoothstep((gates @ z - start) / (full - start))."""
    x = ((z @ gates.T) - ranges[:, 0]) / (ranges[:, 1] - ranges[:, 0])
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


# ---------------------------------------------------------------------------- shading
def _brightness(v: np.ndarray, faces: np.ndarray, light: "ShadeLight | None" = None) -> np.ndarray:
    from ..data.headmodel import vertex_normals

    d, a = (SHADE_LIGHT, SHADE_AMBIENT) if light is None else (light.direction, light.ambient)
    return a + (1.0 - a) * np.clip(vertex_normals(v, faces).astype(np.float64) @ d, 0.0, None)


@dataclass(frozen=True)
class ShadeLight:
    """The light of the expression shading, in the head model's frame: unit ``direction [3]`` (float64,
    towards the light) and the ``ambient`` share of the brightness (``_brightness``)."""

    direction: np.ndarray
    ambient: float


def estimate_light(colors: np.ndarray | Tensor, opacities: np.ndarray | Tensor, binding: "PriorBinding", basis: HeadBasis) -> ShadeLight | None:
    """The light baked into an avatar's neutral colours, for its expression shading; None when it
    cannot be told (the generic ``SHADE_LIGHT`` / ``SHADE_AMBIENT`` then).

    Over the reconstructed Gaussians bound at full weight to the fitted head's face skin
    (``basis.fit_vertices``: every corner of the bound triangle; opacity > 0.5), the linear-light luma
    of the colour (sRGB ** 2.2, Rec. 601 weights) is fitted as ``c0 + c . n`` (first-order spherical
    harmonics; ``n`` the model-frame normal of the fitted neutral head at the bound point), three
    times keeping the ``LIGHT_KEEP`` best-fitting share (albedo that is not skin: lips, brows,
    beard); ``c / |c|`` starts the direction, which a coarse-to-fine search in azimuth and elevation
    (``LIGHT_STEPS_DEG``) refines to the least squares of ``p + q max(n . direction, 0)`` on the same
    points (the harmonics alone were off by ~15 deg: the clamp is not linear in ``n``), whose
    ``ambient = p / (p + q)`` is clipped to ``LIGHT_AMBIENT``. A photo's key light is rarely where the
    generic light sits (the synthetic rig's spans +-75 deg of azimuth; on training subjects the
    estimate is within ~10-25 deg of the true key light), and a crease that the expression turns
    away from the light darkens only if the shading knows which side is lit.

    Args:
        colors ``[N, 3]`` sRGB in [0, 1] and opacities ``[N]`` of the avatar's first N Gaussians
        (the reconstructed ones), binding: their ``PriorBinding`` (at least N rows), basis: the head
        model. Returns None for a basis other than ``ict53``, fewer than ``LIGHT_MIN_POINTS`` skin
        Gaussians, or a fit whose directional part is below ``LIGHT_MIN_CONTRAST`` of its constant one.
    """
    from ..data.headmodel import vertex_normals

    if basis.space != "ict53":
        return None
    col = colors.detach().cpu().numpy() if isinstance(colors, Tensor) else np.asarray(colors)
    op = opacities.detach().cpu().numpy() if isinstance(opacities, Tensor) else np.asarray(opacities)
    n = len(col)
    if op.shape != (n,) or col.shape != (n, 3) or len(binding) < n:
        raise ValueError(f"estimate_light: expected colors [N, 3], opacities [N] and a binding of >= N rows, got {list(col.shape)}, {list(op.shape)} and {len(binding)}")
    ids = binding.vertex_ids[:n].cpu().numpy()
    skin = np.zeros(len(basis.neutral), bool)
    skin[basis.fit_vertices] = True
    sel = (binding.weight[:n].cpu().numpy() > 0.99) & (op > 0.5) & skin[ids].all(1)
    if sel.sum() < LIGHT_MIN_POINTS:
        return None
    ident = binding.identity.double().cpu().numpy()
    v = basis.neutral.astype(np.float64) + np.tensordot(ident, basis.identity_basis[: len(ident)].astype(np.float64), axes=1)
    vn = vertex_normals(v, basis.bind_faces).astype(np.float64)
    nrm = (vn[ids[sel]] * binding.bary[:n].cpu().numpy()[sel, :, None].astype(np.float64)).sum(1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    lin = np.clip(col[sel].astype(np.float64), 0.0, 1.0) ** SHADE_GAMMA @ _LUMA.astype(np.float64)
    A = np.c_[np.ones(len(lin)), nrm]
    keep = np.ones(len(lin), bool)
    for _ in range(3):
        c = np.linalg.lstsq(A[keep], lin[keep], rcond=None)[0]
        r = np.abs(A @ c - lin)
        keep = r <= np.quantile(r, LIGHT_KEEP)
    g = float(np.linalg.norm(c[1:]))
    if not (c[0] > 0 and g > LIGHT_MIN_CONTRAST * c[0]):
        return None
    d = c[1:] / g
    nk, lk = nrm[keep], lin[keep]

    m_l, m_ll = lk.mean(), float(lk @ lk) / len(lk)

    def fit(d):  # p + q max(n . d, 0) by least squares (normal equations) -> (mean squared error, p, q)
        x = np.clip(nk @ d, 0.0, None)
        m_x, m_xx, m_xl = x.mean(), float(x @ x) / len(x), float(x @ lk) / len(x)
        var = m_xx - m_x * m_x
        q = (m_xl - m_x * m_l) / var if var > 1e-12 else 0.0
        p = m_l - q * m_x
        return m_ll - 2 * (p * m_l + q * m_xl) + p * p + 2 * p * q * m_x + q * q * m_xx, p, q

    # the clamped cosine is not linear in n: refine the direction (azimuth, elevation) around the
    # harmonics' estimate, coarse to fine, on the same points
    az, el = math.atan2(d[0], d[2]), math.asin(float(np.clip(d[1], -1.0, 1.0)))
    best = fit(d)
    for step in LIGHT_STEPS_DEG:
        st = math.radians(step)
        cands = [(az + i * st, el + j * st) for i in (-2, -1, 0, 1, 2) for j in (-2, -1, 0, 1, 2)]
        for a, e in cands:
            e = float(np.clip(e, -math.pi / 2, math.pi / 2))
            dd = np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
            r = fit(dd)
            if r[0] < best[0]:
                best, az, el, d = r, a, e, dd
    _, p, q = best
    amb = float(np.clip(p / (p + q), *LIGHT_AMBIENT)) if p + q > 0 else SHADE_AMBIENT
    return ShadeLight(d, amb)


def _srgb_factor(ratio_minus_one: np.ndarray) -> np.ndarray:
    """Linear-light brightness ratio - 1 -> sRGB colour factor - 1 (``SHADE_GAMMA``), same shape/dtype."""
    r = np.asarray(ratio_minus_one)
    return (np.maximum(1.0 + r, 1e-6) ** (1.0 / SHADE_GAMMA) - 1.0).astype(r.dtype)


def shading_basis(identity: np.ndarray, basis: HeadBasis, light: ShadeLight | None = None) -> np.ndarray:
    """``[E, Nv]`` float32: per blendshape ``k`` and vertex, the sRGB colour factor - 1 of the relative
    brightness change, ``(b(head + blendshape_k) / b(head)) ** (1 / SHADE_GAMMA) - 1``, of the head with
    fitted ``identity [K]`` (model frame, ``_brightness`` under ``light``, the avatar's own from
    ``estimate_light``, or None: the generic ``SHADE_AMBIENT``, ``SHADE_LIGHT``; the ratio is of
    linear light, the colours it multiplies are sRGB). The colour factor of an expression ``z`` is
    ``1 + z @ shading_basis`` (linear in ``z``: exact for one blendshape at weight 1, interpolated
    below it, a sum for several), clamped to ``SHADE_RANGE`` per Gaussian. 0 where no
    blendshape moves a vertex. ~0.3 s for the 53 ICT-FaceKit shapes (2 cores), once per avatar on its
    first frame (``PriorRuntime.shade_u``, which evaluates only the vertices its binding uses with
    ``shading_at``); the plain reference for it."""
    k = len(identity)
    v = basis.neutral.astype(np.float64) + np.tensordot(np.asarray(identity, np.float64), basis.identity_basis[:k], axes=1)
    f = basis.bind_faces
    b0 = np.maximum(_brightness(v, f, light), 0.05)
    moving = _moving_vertices(basis)
    out = np.zeros((basis.num_expression, len(v)), np.float32)
    for e in range(basis.num_expression):
        d = basis.expression_basis[e]
        if not np.abs(d).max() > 1e-4:
            continue
        out[e] = np.where(moving, _srgb_factor(_brightness(v + d, f, light) / b0 - 1.0), 0.0)
    return out


def shading_at(identity: np.ndarray, basis: HeadBasis, vertices: np.ndarray, light: ShadeLight | None = None) -> np.ndarray:
    """``shading_basis(identity, basis, light)[:, vertices]`` (``[E, M]`` float32, to float rounding) computed
    only at ``vertices [M]`` (head-model vertex ids): each blendshape's normals on just the triangles
    that touch them, all blendshapes in one numba call (``prior_kernels.shading_rows``, compiled on
    first use and cached). 35-50 ms instead of 0.3-0.4 s (2 cores) for the 53 ICT-FaceKit shapes at
    the ~11k vertices an avatar binds to; the training forward with the prior pays it per sample, a
    served avatar once (``PriorRuntime.shade_u``).

    Args:
        identity: ``[K]`` identity coefficients of the fitted head (``HeadFit.identity``).
        basis: the head model (its ``neutral``, ``identity_basis``, ``expression_basis``, ``bind_faces``).
        vertices: ``[M]`` vertex ids (repeats allowed).
        light: the avatar's light (``estimate_light``), None for the generic one.
    Returns:
        ``[E, M]`` float32; 0 at vertices no blendshape moves.
    """
    from .prior_kernels import shading_rows

    import numba

    from ..render.cpu_backend import num_threads

    vertices = np.asarray(vertices, np.int64).reshape(-1)
    nv = len(basis.neutral)
    e_n = basis.num_expression
    moving = _moving_vertices(basis)
    sel = moving[vertices]  # 0 where no blendshape moves a vertex, as in shading_basis
    want = np.unique(vertices[sel])
    out = np.zeros((e_n, len(vertices)), np.float32)
    if len(want) == 0:
        return out
    vmap = np.full(nv, -1, np.int64)
    vmap[want] = np.arange(len(want))
    f = basis.bind_faces
    faces = np.ascontiguousarray(f[(vmap[f] >= 0).any(axis=1)], dtype=np.int64)  # the normals at `want` need only these
    eb = np.ascontiguousarray(basis.expression_basis, dtype=np.float32)
    rows = np.array([e for e in range(e_n) if np.abs(eb[e]).max() > 1e-4], np.int64)
    got = np.zeros((e_n, len(want)), np.float32)
    identity = np.asarray(identity, np.float64).reshape(-1)
    ib = np.ascontiguousarray(basis.identity_basis[: len(identity)], dtype=np.float32)
    prev = numba.get_num_threads()
    numba.set_num_threads(num_threads())
    try:
        ld, la = (SHADE_LIGHT, SHADE_AMBIENT) if light is None else (np.asarray(light.direction, np.float64), light.ambient)
        shading_rows(np.ascontiguousarray(basis.neutral, dtype=np.float32), ib, identity, eb, rows, faces, vmap, ld, float(la), 0.05, got)
    finally:
        numba.set_num_threads(prev)
    out[:, sel] = _srgb_factor(got[:, vmap[vertices[sel]]])
    return out


# ---------------------------------------------------------------------------- runtime
@functools.lru_cache(maxsize=4)
def _moving_cached(key: int, basis: HeadBasis) -> np.ndarray:
    return np.abs(basis.expression_basis).max(axis=(0, 2)) > 1e-4  # moves more than 0.1 mm

def _moving_vertices(basis: HeadBasis) -> np.ndarray:
    """``[Nv]`` bool: vertices some blendshape moves by more than 0.1 mm."""
    return _moving_cached(id(basis), basis)


_SHARED: dict = {}
_NO_QUATS, _NO_TIDX = np.zeros((0, 4), np.float32), np.zeros(0, np.int32)  # frame() without rotation


def _shared_basis(basis: HeadBasis, device) -> tuple[Tensor, np.ndarray]:
    """The blendshapes of every vertex that moves, ``[E, (1 + Vm) * 3]`` on ``device`` (row 0 = the
    zero slot), and the vertex -> slot map ``[Nv]``; built once per basis and device, shared by
    every avatar (the per-avatar fit's scale and rotation are applied after the gather)."""
    key = (id(basis), str(device))
    if key not in _SHARED:
        moving = _moving_vertices(basis)
        slot = np.zeros(len(moving), np.int64)
        slot[moving] = np.arange(1, int(moving.sum()) + 1)
        bu = np.concatenate([np.zeros((basis.num_expression, 1, 3), np.float32), basis.expression_basis[:, moving]], axis=1)
        with torch.inference_mode(False):  # a normal tensor even when first built inside inference mode
            t = torch.from_numpy(bu.reshape(bu.shape[0], -1)).to(device)
        _SHARED[key] = (t, slot, basis)  # holding basis keeps its id unique
    t, slot, _ = _SHARED[key]
    return t, slot


class PriorRuntime:
    """Per-frame evaluation of a binding.

    ``basis_u [E, U*3]`` holds the blendshapes of every moving vertex of the head model (shared by all
    avatars); ``local [N*3]`` indexes them (slot 0 = a zero row for corners that never move and
    Gaussians with no weight); ``coef [N, 3, 1]`` = barycentric * fade weight; ``M [3, 3]`` = the
    fit's scale * rotation, applied after the gather. ``displacement(z [E])`` -> ``[N, 3]``;
    ``z [B, E]`` -> ``[B, N, 3]``. ``frame`` is the server's per-frame path (one expression, CPU):
    it reads a per-avatar copy of the used slots (``compact``) and writes the deformed Gaussians.
    ``shading(z)`` -> ``[N]`` (``[B, N]``): the colour factor of the expression shading
    (``shading_basis`` under ``light``, the avatar's own from ``estimate_light`` or None for the generic
    one; gathered and weighted like the displacement; 1 everywhere with ``shading=False``).
    ``rotation(z)`` -> ``[N, 4]`` (``[B, N, 4]``) wxyz: each Gaussian's surface rotation (its bound
    triangle's turn between the neutral fitted head and the displaced one, faded by its weight), which
    ``rotate=True`` makes ``frame`` apply to the Gaussians' own rotations (``fastgha._combine`` on the
    other paths).
    """

    def __init__(self, binding: PriorBinding, basis: HeadBasis, device=None, shading: bool = True, rotate: bool = False, light: ShadeLight | None = None):
        dev = device or binding.vertex_ids.device
        self.shading_on = bool(shading)  # expression shading of the reconstructed Gaussians' colours
        self.light = light  # the shading's light (``estimate_light``); None: the generic one
        self.light_of = None  # the colours ``light`` was estimated from (``FastGHA.animate``'s cache key)
        self.rotate_on = bool(rotate)  # bound Gaussians turn with their triangle (``rotation``)
        self._bind_fit = (binding.vertex_ids, binding.transform, binding.identity)  # for ``edges``
        self._edges: Tensor | None = None  # [N, 6], built on first use
        self._tri: tuple | None = None  # frame()'s per-triangle tables (``triangles``)
        self.source = binding  # the binding it was built from (``FastGHA.animate`` sets the avatar's own: its cache key)
        self.identity = binding.identity.detach().cpu().numpy()
        self._shade_u: Tensor | None = None  # [E, U] per slot, built on first use (``shade_u``)
        self.basis_u, slot = _shared_basis(basis, dev)
        ids = binding.vertex_ids.cpu().numpy()  # [N, 3]
        local = slot[ids]
        local[(binding.weight.cpu().numpy() <= 0)] = 0
        self.num_used = int(len(np.unique(local)))
        self.local = torch.from_numpy(local.reshape(-1).astype(np.int64)).to(dev)  # [N*3]
        self.M = binding.transform[:3, :3].float().to(dev)  # [3, 3]
        self.coef = (binding.bary * binding.weight[:, None]).float().to(dev)[..., None]  # [N, 3, 1]
        self.n = len(binding)
        self._W: Tensor | None = None  # built on first use by displacement()
        self._compact: tuple[Tensor, Tensor] | None = None  # built on first use by frame()
        grp = binding.groups()
        self.gated = bool((grp >= 0).any())
        self.group_index = (grp + 1).to(dev)  # [N] into opacity_factors' table
        self.basis = basis
        # for frame(): the gates as tensors, the slots [N, 3], weights [N, 3] and table index [N] int8
        self.gates = torch.as_tensor(basis.gates, dtype=torch.float32).to(dev)  # [G, E]
        self.gate_ranges = torch.as_tensor(basis.gate_ranges, dtype=torch.float32).to(dev)  # [G, 2]
        self.coef3 = self.coef[..., 0].contiguous()  # [N, 3]
        self.group_index8 = self.group_index.to(torch.int8)
        # runs of one gate group among the Gaussians, from the last: (start, end, table slot)
        gi = self.group_index.cpu().numpy()
        cuts = np.flatnonzero(np.diff(gi)) + 1
        starts, ends = np.concatenate([[0], cuts]), np.concatenate([cuts, [self.n]])
        self.runs = [(int(a), int(b), int(gi[a])) for a, b in zip(starts, ends)][::-1]
        self._run_max: tuple | None = None  # frame()'s per-avatar constants, keyed on the Gaussians' tensors

    @staticmethod
    def estimate_nbytes(binding: PriorBinding, basis: HeadBasis, device: str = "cpu", rotate: bool = False) -> int:
        """Bytes a runtime of ``binding`` on ``device`` holds once it has animated a frame: its own
        tensors (the basis shared by every avatar, ``basis_u``, is not counted). On the CPU, the path of
        ``frame`` (per-Gaussian slots and weights, the ``compact`` basis of the ``Uc`` slots the binding
        uses, ``[E, Uc*3]`` float32, and the last frame's opacity reference); elsewhere the path of
        ``displacement`` (the sparse ``W``, its own copy of the slots and weights there). Used by the
        server's avatar budget, where the compact basis is most of it (7.2 MB for the shipped sample's
        avatar, against 6.9 MB of Gaussians). ``rotate``: plus the bound triangles' edges ``[N, 6]``
        float32 and, on the CPU, ``triangles`` (``[N]`` int32 and ``[T, 3 + 15]`` for the ``T``
        distinct bound triangles), a frame's triangle rotations ``[T, 4]`` and rotated quaternions ``[N, 4]``.
        """
        n, e = len(binding), basis.num_expression
        ids = binding.vertex_ids.cpu().numpy()
        local = np.where(_moving_vertices(basis)[ids], ids + 1, 0)
        local[(binding.weight.cpu().numpy() <= 0)] = 0
        used = len(np.unique(local))
        g = len(basis.gates)
        own = n * 3 * 8 + n * 3 * 4 + n * 8 + n + g * e * 4 + g * 2 * 4  # local, coef (= coef3), group index int64 + int8, gates
        own += e * (int(_moving_vertices(basis).sum()) + 1) * 4  # shade_u: the shading per slot
        if rotate:
            own += n * 6 * 4  # edges
            if torch.device(device).type == "cpu":
                t = len(np.unique(ids[binding.weight.cpu().numpy() > 0], axis=0))  # distinct bound triangles
                own += n * 4 + t * (18 + 4) * 4 + n * 4 * 4  # triangles, their rotations, out quats
        if torch.device(device).type == "cpu":
            return own + e * used * 4 * 4 + n * 3 * 4 + n * 4  # compact basis + shading and slots, the opacity reference
        return own + (n + 1) * 8 + n * 3 * 8 + n * 3 * 4  # W: CSR rows, columns, values

    @property
    def W(self) -> Tensor:
        """The gather-and-weight as one sparse ``[N, U]`` CSR matrix (3 entries a row): one sparse product
        per frame instead of an ``[N, 3, 3]`` gather, multiply and sum (1.6 -> ~0.4 ms for 37k Gaussians)."""
        if self._W is None:
            u = self.basis_u.shape[1] // 3
            with warnings.catch_warnings():  # torch marks CSR tensors "beta"; this one is built valid by construction
                warnings.simplefilter("ignore", UserWarning)
                self._W = torch.sparse_csr_tensor(
                    torch.arange(0, 3 * self.n + 1, 3, dtype=torch.int64), self.local.cpu(), self.coef.reshape(-1).cpu(),
                    size=(self.n, u), check_invariants=False,
                ).to(self.basis_u.device)  # [N, U]
        return self._W

    @property
    def compact(self) -> tuple[Tensor, Tensor]:
        """``(basis [E, Uc*4], slots [N, 3] int32)``: for each of the ``Uc`` slots this binding uses, its
        blendshape displacement already in the fit's frame (``M`` applied) and its expression shading
        (``shade_u``), side by side (x, y, z, shade), and each Gaussian's corners as indices into them.
        What ``frame`` reads per frame, in one ``[E] @ [E, Uc*4]`` product whose result the kernel
        gathers one 16-byte row per corner from: for the shipped ``tiny`` avatar of the sample 11.3k of
        19k slots. Built once per runtime (per avatar and binding, ``FastGHA.animate``)."""
        if self._compact is None:
            used, inv = torch.unique(self.local, return_inverse=True)
            e = self.basis_u.shape[0]
            bc = self.basis_u.view(e, -1, 3)[:, used] @ self.M.T  # [E, Uc, 3]
            b4 = torch.cat([bc, self.shade_u[:, used, None].to(bc.dtype)], dim=2)  # [E, Uc, 4]
            self._compact = (b4.reshape(e, -1).contiguous(), inv.view(self.n, 3).to(torch.int32).contiguous())
        return self._compact

    def displacement(self, z: Tensor) -> Tensor:
        z = z.to(self.basis_u.dtype)
        if z.ndim == 1:
            nz = torch.nonzero(z).flatten()
            # a slider frame drives a few blendshapes: read only their rows of the basis
            d = z[nz] @ self.basis_u[nz] if len(nz) * 4 < len(z) else z @ self.basis_u  # [U*3]
            du = d.view(-1, 3) @ self.M.T  # [U, 3], the fit's frame (linear: commutes with the weighting)
            return self.W @ du  # [N, 3]
        b = z.shape[0]
        du = (z @ self.basis_u).view(b, -1, 3) @ self.M.T  # [B, U, 3]
        out = self.W @ du.permute(1, 0, 2).reshape(du.shape[1], 3 * b)  # [N, B*3]
        return out.view(self.n, b, 3).permute(1, 0, 2)  # [B, N, 3]

    @property
    def shade_u(self) -> Tensor:
        """``[E, U]``: ``shading_basis`` of this avatar's fitted identity per slot of ``basis_u`` (0 off,
        and 0 at the slots the binding does not read: ``shading_at`` evaluates only the used ones)."""
        if self._shade_u is None:
            moving = _moving_vertices(self.basis)
            t = np.zeros((self.basis.num_expression, int(moving.sum()) + 1), np.float32)
            if self.shading_on and self.basis.space == "ict53":
                used = np.unique(self.local.cpu().numpy())
                used = used[used > 0]  # slots the binding reads (slot s is moving vertex s - 1)
                t[:, used] = shading_at(self.identity, self.basis, np.flatnonzero(moving)[used - 1], self.light)
            with torch.inference_mode(False):
                self._shade_u = torch.from_numpy(t).to(self.basis_u.device)
        return self._shade_u

    def shading(self, z: Tensor) -> Tensor:
        """Colour factor ``[N]`` for ``z [E]`` (``[B, N]`` for ``[B, E]``): ``1 + sum_k coef_k s[local_k]``
        with ``s = z @ shade_u``, clamped to ``SHADE_RANGE``; applied to the reconstructed Gaussians only."""
        z = z.to(self.basis_u.dtype)
        su = z @ self.shade_u  # [U] or [B, U]
        if z.ndim == 1:
            r = self.W @ su[:, None]  # [N, 1]
            return (1.0 + r[:, 0]).clamp(*SHADE_RANGE)
        return (1.0 + (self.W @ su.T).T).clamp(*SHADE_RANGE)  # [B, N]

    @property
    def edges(self) -> Tensor:
        """``[N, 6]`` float32: each Gaussian's bound triangle's edges ``b - a`` and ``c - a`` on the
        neutral fitted head in the avatar's frame (metres; ``PriorBinding.fitted_vertices``), corners
        in ``vertex_ids`` order. Zero for a Gaussian bound to one vertex (the mouth interior, the
        eyelids, the back shell), whose rotation is then the identity."""
        if self._edges is None:
            ids, transform, identity = self._bind_fit
            b = PriorBinding(ids[:1], torch.zeros(1, 3), torch.zeros(1), transform, identity, self.basis.space)
            v = b.fitted_vertices(self.basis).astype(np.float64)
            tri = v[ids.cpu().numpy()]  # [N, 3, 3]
            e = np.concatenate([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=1).astype(np.float32)
            with torch.inference_mode(False):
                self._edges = torch.from_numpy(np.ascontiguousarray(e)).to(self.basis_u.device)
        return self._edges

    @property
    def triangles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What ``frame`` reads for the rotation, built on first use: ``(tidx [N] int32, tslots [T, 3]
        int32, tgeom [T, 15] float32)``: the ``T`` distinct triangles (corners in ``vertex_ids``
        order) that Gaussians with weight > 0 and a non-degenerate triangle bind to, each Gaussian's
        index among them (-1: none, its rotation is the identity), their corners' slots in the
        ``compact`` basis, and their neutral edges (``edges``) followed by their neutral frame's
        columns x, y, n (``prior_kernels.triangle_rotations``). Fewer triangles than Gaussians (11.6k
        for 34k bound Gaussians of the shipped sample's avatar): the rotation is computed per triangle."""
        if self._tri is None:
            ids = self._bind_fit[0].cpu().numpy()
            e = self.edges.cpu().numpy()
            w = self.coef3.sum(-1).cpu().numpy()
            n1 = np.cross(e[:, :3].astype(np.float64), e[:, 3:].astype(np.float64))
            ok = (w > 0) & (np.linalg.norm(e[:, :3], axis=1) > 1e-12) & (np.linalg.norm(n1, axis=1) > 1e-18)
            tidx = np.full(self.n, -1, np.int32)
            first = np.zeros(0, np.int64)
            if ok.any():
                sel = np.flatnonzero(ok)
                _, first_k, inv = np.unique(ids[sel], axis=0, return_index=True, return_inverse=True)
                tidx[sel] = inv.reshape(-1).astype(np.int32)
                first = sel[first_k]
            slots = self.compact[1].numpy()
            e1, e2 = e[first, :3].astype(np.float64), e[first, 3:].astype(np.float64)
            x = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
            nrm = np.cross(e1, e2)
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
            geom = np.concatenate([e[first], x, np.cross(nrm, x), nrm], axis=1).astype(np.float32)
            self._tri = (tidx, np.ascontiguousarray(slots[first]), np.ascontiguousarray(geom))
        return self._tri

    def rotation(self, z: Tensor) -> Tensor:
        """Surface rotation ``[N, 4]`` wxyz for ``z [E]`` (``[B, N, 4]`` for ``[B, E]``), plain torch.

        Per Gaussian, its bound triangle (corners ``vertex_ids``) on the neutral fitted head and
        displaced by the blendshapes (``du`` of each corner, as ``displacement`` gathers them): the
        orthonormal frame ``F = [x, y, n]`` of each (``x`` along ``b - a``, ``n`` the normal, ``y = n x x``,
        as GaussianAvatars, Qian et al. 2024, orients a triangle) gives the rotation ``R = F_disp F_neutral^T``;
        the result is ``nlerp(identity, q(R), w)`` with ``w`` the Gaussian's fade weight (``sum_k coef_k``,
        barycentrics sum to 1), so unbound Gaussians (weight 0), Gaussians bound to one vertex
        (degenerate triangle) and unmoved triangles get exactly ``(1, 0, 0, 0)``. No gradient flows
        to ``z``; the Gaussians' own rotations take it through ``quaternion_multiply`` (``fastgha._combine``).
        ``prior_kernels.triangle_rotations`` is the same maths (``frame``'s path, once per bound triangle,
        then the weight's nlerp in ``prior_kernels.prior_frame``).
        """
        from .gaussian_head import matrix_to_quaternion

        z = z.detach().to(self.basis_u.dtype)
        lead = z.shape[:-1]
        du = (z @ self.basis_u).view(*lead, -1, 3) @ self.M.T  # [..., U, 3]
        d = du[..., self.local, :].view(*lead, self.n, 3, 3)  # corner displacements
        e = self.edges.view(self.n, 2, 3)
        e1, e2 = e[:, 0], e[:, 1]
        d1, d2 = d[..., 1, :] - d[..., 0, :], d[..., 2, :] - d[..., 0, :]

        def frame(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
            n = torch.linalg.cross(a, b, dim=-1)
            la, ln = a.norm(dim=-1, keepdim=True), n.norm(dim=-1, keepdim=True)
            ok = (la[..., 0] > 1e-12) & (ln[..., 0] > 1e-18)
            x, n = a / la.clamp_min(1e-30), n / ln.clamp_min(1e-30)
            return torch.stack([x, torch.linalg.cross(n, x, dim=-1), n], dim=-1), ok  # columns x, y, n

        f0, ok0 = frame(e1, e2)
        f1, ok1 = frame(e1 + d1, e2 + d2)
        q = matrix_to_quaternion(f1 @ f0.transpose(-1, -2))  # [..., N, 4], w >= 0
        w = self.coef3.sum(-1).clamp(0.0, 1.0)  # [N]
        moved = (d1 != 0).any(-1) | (d2 != 0).any(-1)
        keep = ok0 & ok1 & moved & (w > 0)
        ident = torch.zeros_like(q)
        ident[..., 0] = 1.0
        wq = w[:, None]
        q = (1.0 - wq) * ident + wq * q
        q = q / q.norm(dim=-1, keepdim=True)
        return torch.where(keep[..., None], q, ident)

    def factor_table(self, z: Tensor) -> Tensor:
        """The opacity factor of each gate slot for ``z [E]`` -> ``[2G + 1]`` (``opacity_factors`` is it at ``group_index``)."""
        return factor_table(z.to(self.gates.dtype), self.gates, self.gate_ranges)

    def frame(self, g, n_int: int, dxyz: Tensor, drgb: Tensor, z: Tensor):
        """One frame on the CPU without gradients: canonical ``g`` (N Gaussians, the last ``n_int`` the
        mouth interior / eyelids), the MLP's ``dxyz``, ``drgb [N - n_int, 3]`` and ``z [E]`` -> the
        deformed ``Gaussians``.

        The same Gaussians as the plain path ``fastgha._combine(g, dxyz, drgb, displacement(z), n_int,
        opacity_factors(z), trim=True, shade=shading(z))`` (positions and colours to float32 rounding,
        opacities exactly; with ``rotate`` also ``quats`` = ``quaternion_multiply(rotation(z), g.quats)``),
        from one numba pass (``prior_kernels.prior_frame``), except for which hidden Gaussians are left
        out: a trailing run of one gate group is dropped when every gated opacity in it is below the
        rasterizer's ``ALPHA_MIN`` (the rasterizer skips such splats, so the image is the same), where
        the plain path drops trailing ones only at a gate of exactly 0. ``scales`` and ``features`` of
        the result are views of ``g``'s, and so are ``quats`` without ``rotate`` or at a frame with no
        blendshape weight.
        Raises:
            ValueError: tensors not float32 on the CPU, or shapes that do not match the binding.
        """
        from ..gaussians import Gaussians
        from ..render.projection import ALPHA_MIN
        from .prior_kernels import prior_frame, triangle_rotations

        n, n_rec = len(g), len(g) - n_int
        if n != self.n or dxyz.shape != (n_rec, 3) or drgb.shape != (n_rec, 3) or z.shape != (self.basis_u.shape[0],):
            raise ValueError(
                f"PriorRuntime.frame: expected {self.n} Gaussians, dxyz/drgb [{n_rec}, 3] and z [{self.basis_u.shape[0]}], "
                f"got {n}, {list(dxyz.shape)}, {list(drgb.shape)} and {list(z.shape)}"
            )
        ts = (g.means, g.colors, g.opacities, dxyz, drgb, z, self.basis_u)
        if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in ts):
            raise ValueError("PriorRuntime.frame: expects float32 CPU tensors, got " + ", ".join(f"{t.dtype} on {t.device}" for t in ts))
        # per avatar, kept while g's tensors are the same objects: numpy views of what the kernel
        # reads (a .numpy() call costs ~20 us), the largest canonical opacity of each gate run, and
        # the gates' ranges as gate_factors computes them (so the table below is bit-equal to it)
        c = self._run_max
        if c is None or c[0] is not g.opacities or c[1] is not g.means or c[2] is not g.colors or c[-2] is not g.quats:
            op = g.opacities
            basis_c, slots = self.compact
            rng = self.gate_ranges
            c = self._run_max = (
                op, g.means, g.colors, op.numpy(), g.means.numpy(), g.colors.numpy(),
                [np.float32(op[a:b].max()) if b > a else np.float32(0) for a, b, _ in self.runs],
                basis_c, slots.numpy(), self.coef3.numpy(), self.group_index8.numpy(),
                rng[:, 0].numpy(), (rng[:, 1] - rng[:, 0]).numpy(),
                g.quats, (g.quats.numpy(), *self.triangles) if self.rotate_on else None,
            )
        op_np, means_np, colors_np, run_max, basis_c, slots_np, coef_np, gidx_np, r0, span = c[3:13]
        # factor_table(z) in numpy after the same product: the same float32 operations in the same order
        x = np.clip(((z @ self.gates.T).numpy() - r0) / span, 0.0, 1.0)
        f = x * x * (3.0 - 2.0 * x)
        table = np.concatenate([np.ones(1, np.float32), f, 1.0 - f[1:], 1.0 - f[:1]])  # [2G + 1] float32
        end = n
        for (a, b, slot), omax in zip(self.runs, run_max):
            # the rasterizer keeps a splat when float(opacity) >= ALPHA_MIN; float32 products are monotonic
            if a < n_rec or slot == 0 or not (float(omax * table[slot]) < ALPHA_MIN):
                break
            end = a
        nz = np.flatnonzero(z.numpy())
        # [Uc*4]: per used slot the displacement (the fit's frame) and the shading; a slider frame
        # drives a few blendshapes: read only their rows
        if len(nz) * 4 < len(z):
            nzt = torch.from_numpy(nz)
            d = z[nzt] @ basis_c[nzt]
        else:
            d = z @ basis_c
        out_means, out_colors, out_op = torch.empty(end, 3), torch.empty(end, 3), torch.empty(end)
        rot = self.rotate_on and len(nz) > 0
        out_quats = torch.empty(end if rot else 0, 4)
        import numba

        from ..render.cpu_backend import num_threads

        prev = numba.get_num_threads()
        numba.set_num_threads(num_threads())
        try:
            du = d.view(-1, 4).numpy()
            if rot:
                quats_np, tidx, tslots, tgeom = c[-1]
                tq = np.empty((len(tslots), 4), np.float32)
                triangle_rotations(du, tslots, tgeom, tq)
            else:
                quats_np, tidx, tq = _NO_QUATS, _NO_TIDX, _NO_QUATS
            prior_frame(
                means_np, colors_np, op_np, dxyz.numpy(), drgb.numpy(), du,
                slots_np, coef_np, gidx_np, table, n_rec,
                np.float32(SHADE_RANGE[0]), np.float32(SHADE_RANGE[1]),
                out_means.numpy(), out_colors.numpy(), out_op.numpy(), quats_np, tidx, tq, out_quats.numpy(),
            )
        finally:
            numba.set_num_threads(prev)
        return Gaussians(
            means=out_means, quats=out_quats if rot else g.quats[:end], scales=g.scales[:end], opacities=out_op, colors=out_colors,
            features=None if g.features is None else g.features[:end],
        )

    def displacement_reference(self, z: Tensor) -> Tensor:
        """The plain gather-weight-sum that ``displacement`` computes with one sparse product (tests)."""
        z = z.to(self.basis_u.dtype)
        du = (z @ self.basis_u).view(*z.shape[:-1], -1, 3)  # [..., U, 3]
        out = (du[..., self.local, :].view(*z.shape[:-1], self.n, 3, 3) * self.coef).sum(-2)
        return out @ self.M.T
