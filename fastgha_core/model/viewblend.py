"""View-dependent blending of the input views' Gaussians (unstructured-lumigraph style, issue 17).

Every reconstructed Gaussian comes from one pixel of one input view (its *source view*) and sits on
that view's estimate of the surface. With misregistered inputs (tracked cameras a few mm off, real
photos) all views' Gaussians of the same skin overlap a few mm apart, and a novel view shows their
fusion: doubled features, a blurred face. Image-based rendering solves the same problem by weighting
each input by how close its camera is to the render camera (Buehler et al., "Unstructured Lumigraph
Rendering", SIGGRAPH 2001). Here, per frame, each reconstructed Gaussian's opacity is multiplied by

    factor = exp(-(a[source] - min_{v in covers} a[v]) / tau)

where ``a[v]`` is the angle (degrees) between input camera ``v``'s and the render camera's
direction from the head centre (the world origin of the avatar's frame), and ``covers`` is the set
of input views that see the Gaussian's point (its *coverage mask*, computed at reconstruction:
inside view ``v``'s matte and not occluded in it). The minimum runs over the views that cover the
point, not over all views: a region only side photos see (the temple hair behind a frontal photo's
outline) keeps its best side view at full opacity instead of fading because a frontal camera is
closer to the render camera. The source view always covers its own point, so ``0 < factor <= 1``;
the Gaussian of the closest covering view keeps its opacity.

Per frame the cost is ``V`` angles, a table of the minimum over the ``2^V <= 256`` masks, and
two gathers, an ``exp`` and a product over the ``N`` reconstructed Gaussians.

Gaussians flagged ``under`` (the off-head pixels' Gaussians, ``GaussianHeadConfig.off_head_draw``)
are also moved per frame 1 m deeper along the frame camera's rays and scaled with their distance
(``push_under``): they look the same, but every other Gaussian is composited over them, so they
show only where the head leaves the frame uncovered (hair beside the face, not streaked across it).

Expression penalty (``GaussianHeadConfig.view_blend_expr_mm``, ``ViewBlend.expressions``): the
canonical head is neutral in *geometry* (each photo's tracked expression is undone), but each view's
Gaussians keep that photo's *colours*: a smiling photo's teeth and creases, a profile's open mouth.
Buehler et al. combine several penalties per input; here a second one is added to the angle: with
``d_v = D_g e_v`` the displacement (the expression prior's ict53 basis ``D_g`` of the Gaussian's bound
surface point, metres) of view ``v``'s tracked expression ``e_v`` and ``d_f = D_g e_f`` that of the
frame's expression, ``p[v] = |d_f - d_v|`` in millimetres (how far the point moves between the
photo's expression and the frame's), and the factor becomes

    factor = exp(-(c[source] - min_{v in covers} c[v])),   c[v] = a[v] / tau + p[v] / sigma_mm

(one combined penalty per view, so the covering view best on both keeps full opacity; with every
``p`` equal it is the angle factor above). Only the Gaussians whose covering views' ``d_v`` differ by
more than ``EXPR_SPREAD_FRAC x sigma`` get the combined form (``|p[s] - p[v]| <= |d_s - d_v|``: for the
rest it would change the factor by less than ``1 - exp(-EXPR_SPREAD_FRAC)``, 5%); their ``d_v`` and
their rows of a sparse weight matrix on the prior runtime's compact basis are built once per avatar
and prior binding (``ExpressionPenalty``), so a frame costs one ``[E] @ [E, Uc*4]`` product, a sparse
product and a ``[M, V]`` minimum. The lips of open-mouthed input views, which the prior's mouth gate
fades as the frame's mouth opens (``prior.hide_open_lips``), count in that minimum with ``-ln`` of
their gate factor added: otherwise an open-mouthed frame would pick them, fade the other views' lips,
and the gate would then hide the chosen ones (a hole in the mouth).

Conventions: cameras are ``fastgha_core.cameras.Cameras`` (OpenCV, pixel corners at integer
coordinates); masks are ``uint8`` with bit ``v`` for input view ``v``, so at most 8 views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras import Cameras

__all__ = ["ViewBlend", "angles_deg", "contradicted_by_head_on_view", "blend_factors", "coverage_masks", "min_angle_table", "view_depth_maps", "view_directions", "MAX_BLEND_VIEWS", "COVER_DEPTH_TOL_M", "UNDER_PUSH_M", "push_under",
           "ExpressionPenalty", "expression_factors", "EXPR_SPREAD_FRAC"]

MAX_BLEND_VIEWS = 8  # coverage masks are uint8
UNDER_PUSH_M = 1.0  # push_under: metres the "under" Gaussians move further from the frame's camera (more than a head's depth)
EXPR_SPREAD_FRAC = 0.05  # ExpressionPenalty: Gaussians whose covering views' prior displacements all lie within this x sigma of their source view's get no expression penalty (their factor changes by less than 1 - exp(-0.05), 5%)
COVER_DEPTH_TOL_M = 0.015  # a point counts as seen by a view if at most this far behind that view's surface (metres)


def view_directions(cameras: Cameras) -> Tensor:
    """Unit directions ``[V, 3]`` from the head centre (world origin) to each camera's centre.

    ``cameras`` has batch shape ``[V]`` (or ``[1]``/``[]`` for one camera). Raises ``ValueError`` for a
    camera at the origin.
    """
    c = cameras.centers.reshape(-1, 3).float()
    n = c.norm(dim=-1, keepdim=True)
    if bool((n < 1e-9).any()):
        raise ValueError("view_directions: a camera centre lies at the head centre (world origin); its direction is undefined")
    return c / n


def coverage_masks(
    means: Tensor, cameras: Cameras, foreground: Tensor, depth: Tensor, source_view: Tensor | None = None, tol: float = COVER_DEPTH_TOL_M
) -> Tensor:
    """Which input views see each point: ``uint8 [N]``, bit ``v`` set when view ``v`` covers it.

    Args:
        means: ``[N, 3]`` points (world / head frame, metres).
        cameras: ``[V]`` input cameras, ``V <= 8``, of size ``W x H``.
        foreground: ``[V, H, W]`` matte weight of each view in [0, 1]; a point is inside view ``v``'s
            matte when the pixel it projects into has ``foreground > 0.5``.
        depth: ``[V, H, W]`` camera-space depth (metres) of view ``v``'s visible surface at each pixel
            (``inf`` where nothing is there: nothing occludes). The point is occluded in ``v`` when its
            depth exceeds the largest finite depth of the 3x3 pixels around its pixel by more than
            ``tol`` (the 3x3 maximum forgives a pixel of misregistration at depth edges).
        source_view: ``[N]`` optional view index of each point's own view (``-1`` = none), whose bit is
            always set.
        tol: depth tolerance in metres.
    Raises ``ValueError`` for more than 8 views or mismatched shapes.
    """
    v = int(cameras.batch_shape.numel())
    if v > MAX_BLEND_VIEWS:
        raise ValueError(f"coverage_masks: at most {MAX_BLEND_VIEWS} views fit a uint8 mask, got {v}")
    h, w = cameras.height, cameras.width
    if tuple(foreground.shape) != (v, h, w) or tuple(depth.shape) != (v, h, w):
        raise ValueError(f"coverage_masks: foreground and depth must be [{v}, {h}, {w}], got {list(foreground.shape)} and {list(depth.shape)}")
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"coverage_masks: means must be [N, 3], got {list(means.shape)}")
    cams = cameras.flatten()
    pts = means.detach().float()
    d = depth.float()
    finite = torch.isfinite(d)
    # the largest finite depth of the 3x3 neighbourhood; inf where the pixel itself has no surface
    dmax = F.max_pool2d(torch.where(finite, d, torch.full_like(d, -float("inf")))[:, None], 3, stride=1, padding=1)[:, 0]
    dmax = torch.where(finite, dmax, torch.full_like(d, float("inf")))  # [V, H, W]
    mask = torch.zeros(len(pts), dtype=torch.int32, device=pts.device)
    for i in range(v):
        uv, z = cams[i].to(pts.device, torch.float32).project(pts)  # [N, 2], [N]
        x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h) & (z > 0)
        xi, yi = x.clamp(0, w - 1), y.clamp(0, h - 1)
        fg = foreground[i].to(pts.device)[yi, xi] > 0.5
        seen = z <= dmax[i].to(pts.device)[yi, xi] + tol
        mask |= (inside & fg & seen).int() << i
    if source_view is not None:
        sv = source_view.to(pts.device).long()
        own = sv >= 0
        mask[own] |= (1 << sv[own].clamp(min=0)).int()
    return mask.to(torch.uint8)


def min_angle_table(angles: Tensor) -> Tensor:
    """``[2^V]`` table: for each coverage mask, the smallest angle among its views (``inf`` for mask 0).

    ``angles [V]`` (``V <= 8``), any unit.
    """
    v = angles.shape[0]
    if angles.ndim != 1 or v > MAX_BLEND_VIEWS:
        raise ValueError(f"min_angle_table: angles must be [V] with V <= {MAX_BLEND_VIEWS}, got {list(angles.shape)}")
    m = torch.arange(1 << v, device=angles.device)
    bits = ((m[:, None] >> torch.arange(v, device=angles.device)) & 1).bool()  # [2^V, V]
    return torch.where(bits, angles[None].float(), torch.full((), float("inf"), device=angles.device)).amin(dim=1)


def angles_deg(directions: Tensor, camera: Cameras, offsets: Tensor | None = None) -> Tensor:
    """``[V]`` angles (degrees) between the input ``directions [V, 3]`` and ``camera``'s direction from
    the head centre, plus ``offsets [V]`` degrees when given (mirrored views, ``blend_factors``)."""
    c = view_directions(camera)[0].to(directions)
    ang = torch.rad2deg(torch.arccos((directions @ c).clamp(-1.0, 1.0)))
    return ang if offsets is None else ang + offsets.to(ang)


def blend_factors(source_view: Tensor, mask: Tensor, directions: Tensor, camera: Cameras, tau_deg: float, offsets: Tensor | None = None) -> Tensor:
    """Opacity factors ``[N]`` in (0, 1] for the render ``camera`` (batch ``[1]`` or ``[]``; module doc).

    ``source_view [N]`` int (``-1`` = no source view: factor 1), ``mask [N]`` uint8 coverage masks,
    ``directions [V, 3]`` the input views' unit directions, ``tau_deg > 0`` the fall-off in degrees,
    ``offsets [V]`` (optional, degrees >= 0) added to each view's angle: a view with an offset
    counts as that much further from every render camera (mirrored virtual views, ``model/mirror.py``).
    """
    if tau_deg <= 0:
        raise ValueError(f"blend_factors: tau_deg must be > 0, got {tau_deg}")
    ang = angles_deg(directions, camera, offsets)  # [V]
    table = min_angle_table(ang)  # [2^V]
    sv = source_view.long()
    own = sv >= 0
    a_src = ang[sv.clamp(min=0)]
    a_min = table[mask.long() & ((1 << ang.shape[0]) - 1)]
    f = torch.exp(-(a_src - a_min).clamp(min=0) / float(tau_deg))
    return torch.where(own, f, torch.ones_like(f))


@dataclass
class ViewBlend:
    """Per reconstructed Gaussian: its source view and coverage mask; the input views' directions.

    Attributes:
        source_view: ``int8 [N]`` input view of each reconstructed Gaussian (``-1`` = none).
        mask: ``uint8 [N]`` coverage mask (bit ``v``: input view ``v`` sees the Gaussian's point).
        directions: ``float32 [V, 3]`` unit directions from the head centre to the input cameras.
        offsets: ``float32 [V]`` degrees added to each view's angle to the render camera (None: 0;
            ``blend_factors``): mirrored virtual views (``model/mirror.py``) count as further away
            than the real photos, so real views keep precedence where both see a point.
        sharp: ``bool [N]`` (None: none) Gaussians whose factor is ``exp(-a[source] / (tau x
            sharp_scale))``, by their own camera's angle to the render camera alone: those a more
            head-on view contradicts (``contradicted_by_head_on_view``), whose colour is right only
            seen from their own camera (an overhang, hair the head model lacks), drawn fully there
            and fading fast away from it (the judging view covers their point).
        sharp_scale: the fall-off factor of the ``sharp`` Gaussians (0 < scale <= 1).
        under: ``bool [N]`` (None: none) Gaussians drawn *under* the others in every frame: moved
            ``UNDER_PUSH_M`` further from the frame's camera along its rays and scaled with their
            distance, so that they look the same but every other Gaussian is composited over them
            (``push_under``; the off-head pixels' Gaussians, ``GaussianHeadConfig.off_head_draw``).
        expressions: ``float32 [V, E]`` (None: no expression penalty) each input view's expression
            (known or tracked, the one ``reconstruct`` undid; mirrored views their mirrored one), for
            the expression penalty (module doc, ``ExpressionPenalty``; saved as ``view.expr``).
    """

    source_view: Tensor
    mask: Tensor
    directions: Tensor
    offsets: Tensor | None = None
    sharp: Tensor | None = None
    sharp_scale: float = 0.25
    under: Tensor | None = None
    expressions: Tensor | None = None

    def __post_init__(self) -> None:
        n, v = self.source_view.shape[0], self.directions.shape[0]
        if self.source_view.ndim != 1 or self.mask.shape != (n,) or self.directions.shape != (v, 3) or not 1 <= v <= MAX_BLEND_VIEWS:
            raise ValueError(
                f"ViewBlend: expected source_view [N], mask [N], directions [V<=8, 3]; got {list(self.source_view.shape)}, "
                f"{list(self.mask.shape)}, {list(self.directions.shape)}"
            )
        if n and int(self.source_view.max()) >= v:
            raise ValueError(f"ViewBlend: source_view must be < {v} (the number of directions), got {int(self.source_view.max())}")
        if self.offsets is not None and (self.offsets.shape != (v,) or not bool(torch.isfinite(self.offsets).all()) or bool((self.offsets < 0).any())):
            raise ValueError(f"ViewBlend: offsets must be [V={v}] finite degrees >= 0, got {self.offsets.tolist()}")
        if self.sharp is not None and (self.sharp.shape != (n,) or self.sharp.dtype != torch.bool):
            raise ValueError(f"ViewBlend: sharp must be bool [N={n}], got {self.sharp.dtype} {list(self.sharp.shape)}")
        if self.under is not None and (self.under.shape != (n,) or self.under.dtype != torch.bool):
            raise ValueError(f"ViewBlend: under must be bool [N={n}], got {self.under.dtype} {list(self.under.shape)}")
        if self.expressions is not None and (self.expressions.ndim != 2 or self.expressions.shape[0] != v or not bool(torch.isfinite(self.expressions).all())):
            raise ValueError(f"ViewBlend: expressions must be [V={v}, E] finite, got {list(self.expressions.shape)}")
        if not 0 < float(self.sharp_scale) <= 1:
            raise ValueError(f"ViewBlend: sharp_scale must be in (0, 1], got {self.sharp_scale}")

    def __len__(self) -> int:
        return int(self.source_view.shape[0])

    def factors(self, camera: Cameras, tau_deg: float, expression: Tensor | None = None, sigma_mm: float = 0.0, runtime=None, means: Tensor | None = None) -> Tensor:
        """``[N]`` opacity factors for ``camera``, the same as ``blend_factors``; with the frame's
        ``expression [E]``, ``sigma_mm > 0``, this object's ``expressions`` and the avatar's prior
        ``runtime`` (``prior.PriorRuntime`` of a binding whose first ``N`` Gaussians are these), those
        of the Gaussians whose views' expressions disagree there take the expression penalty too
        (module doc, ``expression_factors``). ``means [N, 3]``: the Gaussians' canonical centres, for
        which of them lie on the lips that open-mouthed views hide (``ExpressionPenalty.build``).

        Per frame: the factor of every (mask, source view) pair, a ``[2^V * V + 1]`` table (the
        last entry 1 for Gaussians without a source view), and one gather of it by each Gaussian's
        pair index (``mask * V + source``, computed once and cached on this object)."""
        if tau_deg <= 0:
            raise ValueError(f"ViewBlend.factors: tau_deg must be > 0, got {tau_deg}")
        v = self.directions.shape[0]
        pairs = (1 << v) * v
        key = self.__dict__.get("_key")
        if key is None or key.device != self.mask.device:
            sv = self.source_view.long()
            key = torch.where(sv >= 0, (self.mask.long() & ((1 << v) - 1)) * v + sv.clamp(min=0), torch.full_like(sv, 2 * pairs))
            if self.sharp is not None:  # the sharp Gaussians' pairs in a second table
                key = torch.where(self.sharp.to(key.device) & (sv >= 0), key + pairs, key)
            self.__dict__["_key"] = key
        ang = angles_deg(self.directions, camera, self.offsets)  # [V]
        table = min_angle_table(ang)  # [2^V]
        f = torch.exp(-(ang[None, :] - table[:, None]).clamp(min=0) / float(tau_deg)).reshape(-1)  # [2^V * V]
        # sharp Gaussians: by their own camera's angle alone (1 there, ~0 a few tau_s away, whatever else covers the point)
        fs = torch.exp(-ang.clamp(min=0) / (float(tau_deg) * float(self.sharp_scale)))[None, :].expand(1 << v, v).reshape(-1)
        out = torch.cat([f, fs, f.new_ones(1)])[key]
        if expression is None or sigma_mm <= 0 or self.expressions is None or runtime is None:
            return out
        pen = self.__dict__.get("_expr")
        spread = EXPR_SPREAD_FRAC * float(sigma_mm) * 1e-3
        if pen is None or pen.runtime is not runtime or pen.idx.device != out.device or pen.with_means != (means is not None) or pen.spread_min_m != spread:
            pen = self.__dict__["_expr"] = ExpressionPenalty.build(self, runtime, spread, means=means)
        if len(pen.idx):  # ``out`` is a new tensor (the gather above)
            out[pen.idx] = pen.factors(ang, expression, tau_deg, sigma_mm, self.sharp_scale)
        return out

    @property
    def nbytes(self) -> int:
        """Bytes held once a frame has been drawn: the tensors and the cached int64 pair index."""
        extra = 0 if self.offsets is None else self.offsets.numel() * self.offsets.element_size()
        extra += 0 if self.sharp is None else self.sharp.numel()
        extra += 0 if self.under is None else self.under.numel()
        extra += 0 if self.expressions is None else self.expressions.numel() * 4
        pen = self.__dict__.get("_expr")  # the expression penalty's tables once built (FastGHA.serving_nbytes bounds them before)
        extra += 0 if pen is None else pen.nbytes
        return sum(t.numel() * t.element_size() for t in (self.source_view, self.mask, self.directions)) + 8 * len(self) + extra

    def subset(self, keep: Tensor) -> "ViewBlend":
        return ViewBlend(self.source_view[keep], self.mask[keep], self.directions, self.offsets, None if self.sharp is None else self.sharp[keep], self.sharp_scale,
                         None if self.under is None else self.under[keep], self.expressions)

    def to(self, device) -> "ViewBlend":
        if self.mask.device == torch.device(device):
            return self  # keeps the cached pair index
        return ViewBlend(
            self.source_view.to(device), self.mask.to(device), self.directions.to(device), None if self.offsets is None else self.offsets.to(device),
            None if self.sharp is None else self.sharp.to(device), self.sharp_scale, None if self.under is None else self.under.to(device),
            None if self.expressions is None else self.expressions.to(device),
        )  # fmt: skip

    def tensors(self) -> dict[str, Tensor]:
        out = {"view.source": self.source_view.to(torch.int8), "view.mask": self.mask.to(torch.uint8), "view.dirs": self.directions.float()}
        if self.offsets is not None:
            out["view.offsets"] = self.offsets.float()
        if self.sharp is not None:
            out["view.sharp"] = self.sharp.to(torch.uint8)
            out["view.sharp_scale"] = torch.tensor([float(self.sharp_scale)])
        if self.under is not None:
            out["view.under"] = self.under.to(torch.uint8)
        if self.expressions is not None:
            out["view.expr"] = self.expressions.float()
        return out

    @staticmethod
    def from_tensors(t: dict[str, Tensor], n: int) -> "ViewBlend | None":
        """From an avatar file's extra tensors; ``None`` when absent (files written before view blending)."""
        keys = ("view.source", "view.mask", "view.dirs")
        if not all(k in t for k in keys):
            return None
        off = t.get("view.offsets")  # absent in files without mirrored views' offsets
        sharp = t.get("view.sharp")  # absent in files without contradicted Gaussians
        scale = t.get("view.sharp_scale")
        under = t.get("view.under")  # absent in files without Gaussians drawn under the others
        expr = t.get("view.expr")  # absent in files written before the expression penalty: angle factors alone
        b = ViewBlend(
            t[keys[0]].to(torch.int8), t[keys[1]].to(torch.uint8), t[keys[2]].float(), None if off is None else off.float(),
            None if sharp is None else sharp.bool(), 0.25 if scale is None else float(scale.reshape(-1)[0]), None if under is None else under.bool(),
            None if expr is None else expr.float(),
        )  # fmt: skip
        if len(b) != n:
            raise ValueError(f"avatar view blend must cover the {n} reconstructed Gaussians, got {len(b)}")
        return b


@dataclass
class ExpressionPenalty:
    """Per-avatar tables of the expression penalty (module doc) for the ``M`` Gaussians that need it.

    Attributes:
        idx: ``[M]`` long, which of the ``N`` reconstructed Gaussians (those whose covering views'
            prior displacements differ from their source view's by more than ``spread_min_m``, metres;
            ``ViewBlend.factors`` uses ``EXPR_SPREAD_FRAC x sigma``).
        source: ``[M, 1]`` long source views; cover: ``[M, V]`` bool coverage bits; sharp: ``[M]`` bool.
        dv: ``[3, M, V]`` each view's expression's prior displacement at the Gaussian (metres),
            coordinate-major (three contiguous ``[M, V]`` planes: the per-frame distances without a
            strided ``[M, V, 3]`` reduction).
        basis: ``[E, Uc*4]`` the prior runtime's own compact basis (``PriorRuntime.compact``: per slot
            the blendshape displacement in the fit's frame and the shading; shared, not copied); W:
            ``[M, Uc]`` sparse CSR, each row the Gaussian's three barycentric x fade weights on its slots.
        runtime: the ``PriorRuntime`` this was built from (the cache key).
        hide: ``[M, V]`` bool: view ``v``'s Gaussians at this point fade as the mouth opens (the lips of
            an open-mouthed view, ``prior.hide_open_lips``): per frame ``-ln(1 - gate)`` is added to
            that view's penalty in the minimum, so a frame with an open mouth does not fade the other
            views' lips in favour of lips that the gate hides (None: none).
        with_means, spread_min_m: how it was built (``ViewBlend.factors``' cache key).
    """

    idx: Tensor
    source: Tensor
    cover: Tensor
    sharp: Tensor
    dv: Tensor
    basis: Tensor
    W: Tensor
    runtime: object
    hide: Tensor | None = None
    with_means: bool = False
    spread_min_m: float = 0.0

    @staticmethod
    def build(blend: "ViewBlend", runtime, spread_min_m: float = 0.0, means: Tensor | None = None) -> "ExpressionPenalty":
        """From ``blend`` (with ``expressions [V, E]``) and a ``prior.PriorRuntime`` whose first ``N``
        Gaussians are ``blend``'s; with their canonical centres ``means [N, 3]`` also ``hide`` (the
        open-mouthed views, ``prior.open_mouth_views``, at the points within ``prior.LIP_RADIUS`` of the
        fitted head's lip landmarks, as ``prior.hide_open_lips`` chooses them). Raises ``ValueError``
        when the runtime holds fewer Gaussians or another expression dimension."""
        import warnings

        n, v = len(blend), blend.directions.shape[0]
        bu = runtime.basis_u
        e = bu.shape[0]
        dev = blend.mask.device
        if blend.expressions is None or blend.expressions.shape != (v, e):
            got = None if blend.expressions is None else list(blend.expressions.shape)
            raise ValueError(f"ExpressionPenalty: the blend's expressions (an avatar file's view.expr) must be [V={v}, E={e}] "
                             f"(E: the prior runtime's expression dimension), got {got}")
        if runtime.n < n:
            raise ValueError(f"ExpressionPenalty: the prior runtime holds {runtime.n} Gaussians, the blend {n}")
        coef_all = runtime.coef3[:n].to(dev, torch.float32)
        dv_all = runtime.displacement(blend.expressions.to(bu.device, bu.dtype))[:, :n].to(dev, torch.float32)  # [V, N, 3]
        sv = blend.source_view.to(dev).long()
        own = sv >= 0
        bits = ((blend.mask.to(dev).long()[:, None] >> torch.arange(v, device=dev)) & 1).bool()  # [N, V]
        ds = dv_all[sv.clamp(min=0), torch.arange(n, device=dev)]  # [N, 3]
        spread = torch.where(bits.T, (dv_all - ds[None]).norm(dim=-1), torch.zeros((), device=dev)).amax(dim=0)  # [N]
        idx = (own & (spread > float(spread_min_m))).nonzero()[:, 0]
        m = len(idx)
        basis, cslots = runtime.compact  # [E, Uc*4], [N_all, 3]
        basis = basis.to(dev, torch.float32)
        with warnings.catch_warnings():  # torch marks CSR tensors "beta"; this one is valid by construction
            warnings.simplefilter("ignore", UserWarning)
            W = torch.sparse_csr_tensor(
                torch.arange(0, 3 * m + 1, 3, dtype=torch.int64, device=dev), cslots[:n].to(dev).long()[idx].reshape(-1), coef_all[idx].reshape(-1),
                size=(m, basis.shape[1] // 4), check_invariants=False,
            )  # fmt: skip
        sharp = blend.sharp.to(dev)[idx] if blend.sharp is not None else torch.zeros(m, dtype=torch.bool, device=dev)
        hide = None
        b, hb = getattr(runtime, "source", None), getattr(runtime, "basis", None)
        if means is not None and b is not None and hb is not None and hb.lip_landmarks is not None and m:
            from .prior import LIP_RADIUS, open_mouth_views

            ov = torch.from_numpy(open_mouth_views(blend.expressions, hb)).to(dev)
            if bool(ov.any()):
                scale = float(torch.linalg.det(b.transform[:3, :3].double().cpu()).abs() ** (1 / 3))
                lips = torch.from_numpy(b.fitted_vertices(hb)[hb.lip_landmarks]).to(dev)
                near = torch.cdist(means[:n][idx].detach().float().to(dev), lips).amin(dim=1) < LIP_RADIUS * scale
                hide = near[:, None] & ov[None, :] & (b.weight[:n].to(dev)[idx] > 0)[:, None]
                hide = hide if bool(hide.any()) else None
        dv = dv_all[:, idx].permute(2, 1, 0).contiguous()  # [3, M, V]
        return ExpressionPenalty(idx, sv[idx, None], bits[idx], sharp, dv, basis, W, runtime, hide, means is not None, float(spread_min_m))

    def __len__(self) -> int:
        return int(self.idx.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of these tables (the runtime's compact basis not counted: ``PriorRuntime.estimate_nbytes``)."""
        extra = 0 if self.hide is None else self.hide.numel()
        extra += 36 * len(self) + 8 * (len(self) + 1)  # W: 3 columns (int64) and 3 weights a row, row pointers
        return extra + sum(t.numel() * t.element_size() for t in (self.idx, self.source, self.cover, self.sharp, self.dv))

    @staticmethod
    def estimate_nbytes(n: int, v: int) -> int:
        """An upper bound of ``nbytes`` for ``n`` Gaussians and ``v`` views (every Gaussian penalised)."""
        return n * (8 + 8 + 2 * v + 1 + 12 * v + 36) + 8 * (n + 1)

    def frame_displacement(self, expression: Tensor) -> Tensor:
        """``[M, 3]`` the prior displacement ``D_g e`` of ``expression [E]`` at these Gaussians (metres)."""
        z = torch.as_tensor(expression, dtype=torch.float32).to(self.basis.device).reshape(-1)
        return self.W @ (z @ self.basis).view(-1, 4)[:, :3].contiguous()  # [Uc, 3] -> [M, 3]

    def penalties_mm(self, expression: Tensor) -> Tensor:
        """``[M, V]`` ``|D_g (e_frame - e_v)|`` in millimetres."""
        df = self.frame_displacement(expression).T  # [3, M]
        x = self.dv[0] - df[0, :, None]
        p = x * x
        for k in (1, 2):
            x = self.dv[k] - df[k, :, None]
            p.addcmul_(x, x)
        return p.sqrt_().mul_(1000.0)

    def factors(self, ang: Tensor, expression: Tensor, tau_deg: float, sigma_mm: float, sharp_scale: float = 0.25) -> Tensor:
        """``[M]`` factors of these Gaussians for the frame's per-view angles ``ang [V]`` (degrees, offsets
        included) and ``expression [E]`` (``expression_factors``)."""
        hidden = None
        if self.hide is not None:
            z = torch.as_tensor(expression, dtype=torch.float32).reshape(-1)
            h = float(self.runtime.factor_table(z.to(self.runtime.gates.device))[-1])  # 1 - the mouth gate (prior.opacity_factors' last slot)
            hidden = torch.where(self.hide, -math.log(max(h, 1e-6)), 0.0) if h < 1 else None
        return expression_factors(ang, self.penalties_mm(expression), self.source[:, 0], self.cover, tau_deg, sigma_mm, self.sharp, sharp_scale, hidden)


def expression_factors(
    ang: Tensor, p_mm: Tensor, source: Tensor, cover: Tensor, tau_deg: float, sigma_mm: float, sharp: Tensor | None = None, sharp_scale: float = 0.25,
    hidden: Tensor | None = None,
) -> Tensor:
    """Opacity factors ``[M]`` with the expression penalty (module doc).

    ``ang [V]`` degrees (the frame camera's angle to each input view's), ``p_mm [M, V]`` each view's
    expression penalty ``|d_frame - d_v|`` (millimetres: how far the point moves between view ``v``'s
    expression and the frame's), ``source [M]`` long (>= 0), ``cover [M, V]`` bool (the source's bit
    set), ``tau_deg, sigma_mm > 0``. ``c[v] = ang[v] / tau + p_mm[v] / sigma``, factor
    ``exp(-(c[source] - min over covering v of c[v]))``; ``sharp [M]`` Gaussians:
    ``exp(-ang[source] / (tau sharp_scale))`` times the expression part alone,
    ``exp(-(p[source] - min over covering v of p[v]) / sigma)``. ``hidden [M, V]`` (optional, >= 0):
    added to ``c[v]`` (and ``p[v] / sigma``) in the minimum but not to the source's own term: ``-ln``
    of the gate factor that view's Gaussians there are drawn with (their own opacity already carries
    it), so a view the gate hides does not fade the others.
    """
    if tau_deg <= 0 or sigma_mm <= 0:
        raise ValueError(f"expression_factors: tau_deg and sigma_mm must be > 0, got {tau_deg}, {sigma_mm}")
    p = p_mm / float(sigma_mm)  # [M, V]
    c = p + ang.to(p)[None, :] / float(tau_deg)
    hp = p if hidden is None else p + hidden.to(p)
    hc = c if hidden is None else c + hidden.to(p)
    inf = torch.full((), float("inf"), device=p.device)
    s = source.long()[:, None]
    f = torch.exp(-(c.gather(1, s)[:, 0] - torch.where(cover, hc, inf).amin(dim=1)).clamp(min=0))
    if sharp is not None and bool(sharp.any()):
        fe = torch.exp(-(p.gather(1, s)[:, 0] - torch.where(cover, hp, inf).amin(dim=1)).clamp(min=0))
        fs = torch.exp(-ang.to(p)[source.long()].clamp(min=0) / (float(tau_deg) * float(sharp_scale))) * fe
        f = torch.where(sharp, fs, f)
    return f


def view_depth_maps(means: Tensor, cameras: Cameras, visible: Tensor) -> Tensor:
    """``[V, S, S]`` camera-space depth of each view's own pixel-aligned Gaussians (``inf`` where not ``visible``).

    ``means [V*S*S, 3]`` view-major (``GaussianHead`` order), ``cameras [V]`` of size ``S x S``,
    ``visible [V*S*S]`` bool.
    """
    v = int(cameras.batch_shape.numel())
    s = cameras.height
    if means.shape[0] != v * s * cameras.width:
        raise ValueError(f"view_depth_maps: expected {v}x{s}x{cameras.width} view-major means, got {means.shape[0]}")
    pts = means.detach().float().reshape(v, -1, 3)
    z = cameras.flatten().to(pts.device, torch.float32).world_to_camera(pts)[..., 2]  # [V, S*S]
    z = torch.where(visible.reshape(v, -1), z, torch.full_like(z, float("inf")))
    return z.reshape(v, s, cameras.width)


def contradicted_by_head_on_view(
    means: Tensor,
    colors: Tensor,
    source_view: Tensor,
    mask: Tensor,
    cameras: Cameras,
    images: Tensor,
    centre: Tensor | None = None,
    views: int | None = None,
    gain_deg: float = 15.0,
    colour_tol: float = 0.25,
) -> Tensor:
    """``bool [N]``: Gaussians whose colour the input view that sees their point most head-on contradicts.

    Why (issue 17, the real photo sets' orbit renders): a view from below (a pitch-up photo) sees the
    underside of a fringe that overhangs the forehead; the tracked head has no hair there, so those
    pixels' rays end on the forehead skin and their Gaussians draw a wedge of hair on the forehead
    wherever that view is about as near the render camera as the frontal photo. The frontal photo
    sees the same skin head-on and shows skin there: the two views disagree, and the one that sees
    the point more squarely is the one to believe (a grazing or occluded look at a point is where an
    unmodelled overhang, hair volume or misregistration puts the wrong colour on it).

    For each Gaussian with a source view ``s`` among the first ``views`` (the real photos; mirrored
    views are neither judged nor judges), the *judge* is the covering view ``r != s`` among them
    (``mask`` bit) whose direction from the point is nearest the point's outward direction from
    ``centre`` (the head centre: a radial normal, the head being round at the scale of a hair
    overhang). It is contradicted when the judge sees it at least ``gain_deg`` degrees more squarely
    than its source does, and the judge's image at the point's projection differs from the
    Gaussian's colour by more than ``colour_tol`` in some channel (0..1, sRGB).

    Args:
        means ``[N, 3]``, colors ``[N, 3]``: the reconstructed Gaussians (world, metres; RGB in [0, 1]).
        source_view ``[N]`` int, mask ``[N]`` uint8: as ``ViewBlend`` (``coverage_masks``).
        cameras ``[V]`` of size ``W x H``, images ``[V, 3, H, W]`` in [0, 1]: the input views.
        centre ``[3]``: the head centre (world; default the origin, the tracker's head frame).
        views: how many of the leading views take part (default all ``V``).
    Raises ``ValueError`` for mismatched shapes.
    """
    v = int(cameras.batch_shape.numel())
    h, w = cameras.height, cameras.width
    if tuple(images.shape) != (v, 3, h, w):
        raise ValueError(f"contradicted_by_head_on_view: images must be [{v}, 3, {h}, {w}], got {list(images.shape)}")
    n = means.shape[0]
    if colors.shape != (n, 3) or source_view.shape != (n,) or mask.shape != (n,):
        raise ValueError("contradicted_by_head_on_view: means, colors, source_view and mask must describe the same N Gaussians")
    nv = v if views is None else int(views)
    cams = cameras.flatten().to(means.device, torch.float32)
    pts = means.detach().float()
    c0 = torch.zeros(3, device=pts.device) if centre is None else torch.as_tensor(centre, dtype=torch.float32, device=pts.device)
    radial = F.normalize(pts - c0, dim=-1)
    to_cam = F.normalize(cams.centers.reshape(v, 1, 3)[:nv] - pts[None], dim=-1)  # [nv, N, 3]
    cosang = (to_cam * radial[None]).sum(-1)  # [nv, N]: larger = more head-on
    sv = source_view.long().to(pts.device)
    real = (sv >= 0) & (sv < nv)
    bits = ((mask.long().to(pts.device)[None] >> torch.arange(nv, device=pts.device)[:, None]) & 1).bool()  # [nv, N]
    cand = bits & (torch.arange(nv, device=pts.device)[:, None] != sv[None])
    score = torch.where(cand, cosang, torch.full_like(cosang, -2.0))
    best, judge = score.max(dim=0)
    own = cosang.gather(0, sv.clamp(0, nv - 1)[None])[0]
    gain = torch.rad2deg(torch.arccos(own.clamp(-1, 1))) - torch.rad2deg(torch.arccos(best.clamp(-1, 1)))
    check = real & (best > -2.0) & (gain >= gain_deg)
    out = torch.zeros(n, dtype=torch.bool, device=pts.device)
    idx = check.nonzero()[:, 0]
    if len(idx) == 0:
        return out
    j = judge[idx]
    seen = torch.empty(len(idx), 3, device=pts.device)
    for r in range(nv):
        sel = j == r
        if not bool(sel.any()):
            continue
        uv, _ = cams[r].project(pts[idx[sel]])
        grid = torch.stack([uv[:, 0] / w * 2 - 1, uv[:, 1] / h * 2 - 1], -1)[None, None]  # align_corners=False: pixel corners at integers
        seen[sel] = F.grid_sample(images[r : r + 1].to(pts.device, torch.float32), grid, mode="bilinear", align_corners=False, padding_mode="border")[0, :, 0].T
    out[idx] = (seen - colors[idx].float().to(pts.device)).abs().amax(-1) > colour_tol
    return out


def push_under(means: Tensor, scales: Tensor, camera: Cameras, select: Tensor, push_m: float = UNDER_PUSH_M) -> tuple[Tensor, Tensor]:
    """The ``select``-ed Gaussians moved ``push_m`` metres deeper along ``camera``'s rays, looking the same.

    Each selected Gaussian is scaled about the camera centre by ``k = (z + push_m) / z`` (``z`` its
    camera-space depth): its mean goes to ``c + k (mean - c)`` and its scales are multiplied by
    ``k``. Under a perspective camera its projection is unchanged (the EWA splat's 2D covariance
    ``J Sigma J^T`` is invariant: ``Sigma`` scales by ``k^2``, the Jacobian ``J`` by ``1/k``), but it is
    now ``push_m`` deeper, so a depth-sorting rasteriser composites every Gaussian less than
    ``push_m`` behind its old depth over it: for the frame, it is drawn *under* the others (only
    where they leave the pixel uncovered). Gaussians behind the camera (``z <= 0``) are not moved.

    Args:
        means ``[N, 3]``, scales ``[N, 3]``: world / head frame, metres.
        camera: one camera (batch ``[1]`` or ``[]``; OpenCV, ``cameras.py``).
        select: ``bool [N]``.
    Returns:
        ``(means, scales)``, new tensors.
    Raises:
        ValueError: on mismatched shapes or ``push_m < 0``.
    """
    if means.shape != scales.shape or means.ndim != 2 or means.shape[-1] != 3 or select.shape != means.shape[:1]:
        raise ValueError(f"push_under: means, scales [N, 3] and select [N] expected, got {list(means.shape)}, {list(scales.shape)}, {list(select.shape)}")
    if push_m < 0:
        raise ValueError(f"push_under: push_m must be >= 0, got {push_m}")
    cam = camera.flatten()[0] if camera.batch_shape.numel() == 1 and len(camera.batch_shape) else camera
    cam = cam.to(means.device, means.dtype)
    idx = select.to(means.device).nonzero()[:, 0]  # only the selected ones are touched (a few thousand per frame)
    m = means[idx]
    z = cam.world_to_camera(m)[..., 2]
    k = torch.where(z > 0, (z + float(push_m)) / z.clamp_min(1e-9), torch.ones_like(z))[:, None]
    c = cam.centers.reshape(3)
    out_m, out_s = means.clone(), scales.clone()
    out_m[idx] = c + k * (m - c)
    out_s[idx] = scales[idx] * k
    return out_m, out_s

