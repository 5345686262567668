r"""Residuals and analytic Jacobian of the paper's energy for B subjects seen in V views each.

Parameters of one subject, packed in this order:

- shape ``y`` (K), then expression ``e`` (E) if fitted;
- per view: ``(roll, pitch, yaw)``, ``t`` (3) and, if fitted, the intrinsics as ``(log f, u0, v0)``:
  the logarithm keeps the focal length positive whatever step the solver takes, and makes the
  focal prior (a relative spread ``σ_f / f``) a plain quadratic in the parameter.

Residuals of one subject: the normal term of every view's visible vertices (3 per vertex, padded to
a common count ``S``), the landmark term of every view (2 per landmark), the shape prior (K), an
expression prior if fitted, and an intrinsics prior per view if fitted. With
:math:`X = X_0 + W y + E e`, :math:`X_c = R (X + t)`, :math:`a = \pi_K(X_c)` and :math:`n_c = R\, n(X)`,
the normal residual is :math:`r = \sqrt{\lambda_N}\,(N(a) - n_c)` and its Jacobian

.. math::

    \frac{\partial r}{\partial \xi} = \sqrt{\lambda_N}\Big(\nabla N(a)\,\frac{\partial a}{\partial \xi}
    - \frac{\partial n_c}{\partial \xi}\Big),

with :math:`\nabla N` from :func:`~facenormals.sampling.sample_bicubic_with_gradient` and
:math:`\partial a / \partial X_c` from :func:`~facenormals.geometry.projection_jacobian`. For the
shape, :math:`\partial r_i / \partial y = \sum_g A_{ig} W_g` over the ring of vertex :math:`i`, with
3×3 blocks :math:`A_{ig} = \sqrt{\lambda_N}(\delta_{ig} \nabla N\, \partial a / \partial X_c\, R - R M_{ig})`
and the normal derivative blocks :math:`M_{ig}` of :class:`~facenormals.fitting.rings.Rings`: all
normal rows are one sparse (CSR) product with the basis rows :math:`W`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor
from torch._C._functorch import is_functorch_wrapped_tensor

from facenormals.core.check import check_all_finite, check_floating, check_real, check_shape
from facenormals.energy import prior_residuals
from facenormals.energy.residuals import _foreground_at, _landmark_differences, _support_foreground
from facenormals.fitting.rings import RingRows, Rings
from facenormals.fitting.robust import cauchy_weights, check_scale, huber_weights
from facenormals.geometry import (
    euler_rotation_derivatives,
    euler_to_rotation_matrix,
    project_points,
    projection_jacobian,
    transform_points,
)
from facenormals.mesh import vertex_normals
from facenormals.models import MorphableModel
from facenormals.optim.normal_equations import gram
from facenormals.render import rasterize_depth, splat_zbuffer, visible_vertices
from facenormals.sampling import BicubicSampler

__all__ = ["FitWeights", "HeadFitProblem"]


@dataclass(frozen=True)
class FitWeights:
    """Weights of the energy terms (the paper's defaults) and of the extra priors.

    Attributes:
        normals: λN of EN.
        landmarks: λZ of EZ.
        prior: λP of the shape prior EP.
        expression_prior: weight of ½‖e‖² when expressions are fitted.
        focal_std: standard deviation of the log-normal focal-length prior (of ``log f``; about the
            relative spread ``σ_f / f_prior``).
        center_std: standard deviation of the principal-point prior, pixels.
    """

    normals: float = 1.0
    landmarks: float = 0.8
    prior: float = 0.4
    expression_prior: float = 1.0
    focal_std: float = 0.2
    center_std: float = 4.0

    def __post_init__(self) -> None:
        for name, positive in (("normals", False), ("landmarks", False), ("prior", False),
                               ("expression_prior", False), ("focal_std", True), ("center_std", True)):
            value = getattr(self, name)
            number = check_real(value, f"FitWeights.{name}")  # a string from a config file failed deep in the fit
            if not (number > 0 if positive else number >= 0):
                raise ValueError(f"FitWeights.{name}: expected a finite number {'> 0' if positive else '>= 0'}, "
                                 f"got {value!r}")
            object.__setattr__(self, name, number)  # a plain float: numpy or 0-d tensor values too


@dataclass
class _Layout:
    """The sparse structure of a round for a list of subjects (see :meth:`HeadFitProblem._layout`)."""

    rings: Rings
    slot: Tensor  # (K, V, S) ring slot of each residual vertex, ``U`` for padding
    vertex: Tensor  # (K, V, S) flat vertex id ``k N + i``
    rows: RingRows
    pair_view: Tensor  # (T,) flat (subject, view) of each (entry, block) pair
    diagonal: Tensor  # (D,) the pairs whose block column is the entry's own vertex


class HeadFitProblem:
    """The fitting energy of ``B`` subjects with ``V`` views each, for :func:`levenberg_marquardt`.

    Every evaluation method takes an optional ``index`` ``(K,)`` of the subjects that ``x`` ``(K, P)``
    holds, so that a solver can evaluate only its unfinished batch elements.

    Args:
        model: the morphable model (its dtype is the problem's dtype).
        normal_maps: ``(B, V, 3, H, W)`` camera-frame normal maps, zero on background.
        landmarks: ``(B, V, L, 2)`` detected landmarks of the model's landmark list, pixels.
        landmark_mask: ``(B, V, L)`` which landmarks are present (a non-finite landmark counts as absent).
        intrinsics_prior: ``(B, V, 3)`` prior ``(f, u0, v0)``; also the fixed intrinsics when they
            are not fitted.
        weights: the :class:`FitWeights`.
        fit_intrinsics: fit ``(f, u0, v0)`` per view.
        fit_expression: fit expression coefficients (shared by the views).
        view_weights: ``(B, V)`` extra weight of each view's normal term (e.g. 0 for a view whose
            map has no foreground).
        vertex_subset: ``(N,)`` or per subject ``(B, N)`` bool, the vertices the normal term may use
            (default: all), e.g.
            :func:`~facenormals.fitting.subsample.grid_subset` of the mean head.

    The maps are sampled through a :class:`~facenormals.sampling.BicubicSampler`, whose table
    holds about 16× the maps (3.4 MB per 128² view in float32).
    """

    def __init__(
        self,
        model: MorphableModel,
        normal_maps: Tensor,
        landmarks: Tensor,
        landmark_mask: Tensor,
        intrinsics_prior: Tensor,
        weights: FitWeights = FitWeights(),
        fit_intrinsics: bool = True,
        fit_expression: bool = False,
        view_weights: Tensor | None = None,
        vertex_subset: Tensor | None = None,
    ) -> None:
        if not isinstance(model, MorphableModel):
            raise ValueError(f"model: expected a MorphableModel, got {type(model).__name__}")
        dims = check_shape(normal_maps, ["B", "V", 3, "H", "W"], "normal_maps")
        check_floating(normal_maps, "normal_maps")
        if min(normal_maps.shape) < 1:  # nothing to fit; the ring and visibility layout would fail deep inside
            raise ValueError(f"normal_maps: expected at least one subject, one view and one pixel, got shape "
                             f"{tuple(normal_maps.shape)}")
        views = {"B": dims["B"], "V": dims["V"]}
        check_shape(landmarks, ["B", "V", model.landmark_indices.shape[0], 2], "landmarks", views)
        check_floating(landmarks, "landmarks")  # bool or integer landmarks would fit silently
        check_shape(landmark_mask, ["B", "V", model.landmark_indices.shape[0]], "landmark_mask", views)
        if landmark_mask.dtype != torch.bool:
            raise ValueError(f"landmark_mask: expected a bool tensor, got dtype {landmark_mask.dtype}")
        check_shape(intrinsics_prior, ["B", "V", 3], "intrinsics_prior", views)
        check_floating(intrinsics_prior, "intrinsics_prior")  # a bool prior read as f = u0 = v0 = 1
        # NaN maps would read as background and NaN landmarks as zero-cost: name them instead
        check_all_finite(normal_maps=normal_maps, intrinsics_prior=intrinsics_prior)
        landmark_mask = landmark_mask & torch.isfinite(landmarks).all(-1)  # NaN marks a missing landmark
        if view_weights is not None:
            check_shape(view_weights, ["B", "V"], "view_weights", views)
            if not bool((torch.isfinite(view_weights) & (view_weights >= 0)).all()):
                raise ValueError("view_weights: expected finite values >= 0")
        self.model = model
        self.B, self.V = dims["B"], dims["V"]
        self.H, self.W = dims["H"], dims["W"]
        self.N = model.num_vertices
        self.K = model.num_shape
        self.E = model.num_expressions if fit_expression else 0
        self.C = self.K + self.E
        self.fit_intrinsics = fit_intrinsics
        self.per_view = 9 if fit_intrinsics else 6
        self.P = self.C + self.V * self.per_view
        self.dtype = model.mean.dtype
        device = normal_maps.device
        self.normal_maps = normal_maps.to(self.dtype)
        # The maps are fixed: their bicubic taps and foreground supports are tabulated once.
        flat_maps = self.normal_maps.reshape(-1, 3, self.H, self.W)
        self._sampler = BicubicSampler(flat_maps)
        self._support = _support_foreground(flat_maps)  # (B V, H W)
        self.landmarks = landmarks.to(self.dtype)
        self.landmark_mask = landmark_mask
        if not bool((intrinsics_prior[..., 0] > 0).all()):
            raise ValueError("intrinsics_prior: expected focal lengths f > 0, got "
                             f"{intrinsics_prior[..., 0].min().item():g}")
        self.intrinsics_prior = intrinsics_prior.to(self.dtype)
        self.weights = weights
        ones = torch.ones(self.B, self.V, dtype=self.dtype, device=device)
        self.view_weights = ones if view_weights is None else view_weights.to(self.dtype)
        self.vertex_subset = vertex_subset
        self.lm_index = model.landmark_indices
        self.basis_landmarks = self._basis(self.dtype).view(self.N, 3, self.C)[self.lm_index]  # (L, 3, C)
        self.L = self.lm_index.shape[0]
        self.prior_jacobian = self._prior_jacobian()
        self.set_visibility(torch.zeros(self.B, self.V, self.N, dtype=torch.bool, device=device))

    # ------------------------------------------------------------------------------------------
    # Parameters
    # ------------------------------------------------------------------------------------------

    def pack(self, shape: Tensor, angles: Tensor, translation: Tensor, intrinsics: Tensor,
             expression: Tensor | None = None) -> Tensor:
        """Parameters ``(B, P)`` from shape ``(B, K)``, per-view angles, translations, intrinsics ``(B, V, 3)``
        (``(f, u0, v0)``; stored as ``(log f, u0, v0)``)."""
        parts = [shape]
        if self.E:
            parts.append(expression if expression is not None else shape.new_zeros(self.B, self.E))
        if self.fit_intrinsics:
            intrinsics = torch.cat([intrinsics[..., :1].log(), intrinsics[..., 1:]], dim=-1)
        view = [angles, translation] + ([intrinsics] if self.fit_intrinsics else [])
        parts.append(torch.cat(view, dim=-1).reshape(self.B, -1))
        return torch.cat(parts, dim=1)

    def unpack(self, x: Tensor, index: Tensor | None = None) -> dict[str, Tensor]:
        """The named parameters of ``x`` ``(K, P)`` (the subjects ``index``, default all)."""
        out = {"shape": x[:, : self.K]}
        out["expression"] = x[:, self.K : self.C] if self.E else None
        views = x[:, self.C :].reshape(x.shape[0], self.V, self.per_view)
        out["angles"], out["translation"] = views[..., 0:3], views[..., 3:6]
        if self.fit_intrinsics:
            out["intrinsics"] = torch.cat([views[..., 6:7].exp(), views[..., 7:9]], dim=-1)
        else:
            out["intrinsics"] = self._pick(self.intrinsics_prior, index)
        return out

    def vertices(self, x: Tensor, index: Tensor | None = None) -> Tensor:
        """Model-frame vertices ``(K, N, 3)``."""
        p = self.unpack(x, index)
        return self.model(p["shape"], p["expression"]) if self.E else self.model(p["shape"])

    @staticmethod
    def _pick(t: Tensor, index: Tensor | None) -> Tensor:
        return t if index is None else t.index_select(0, index)

    def _views(self, x: Tensor, index: Tensor | None):
        """Parameters, vertices (K, N, 3), and per (subject, view) R (KV, 3, 3), t (KV, 3), K (KV, 3)."""
        p = self.unpack(x, index)
        verts = self.model(p["shape"], p["expression"]) if self.E else self.model(p["shape"])
        R = euler_to_rotation_matrix(p["angles"].reshape(-1, 3))
        return p, verts, R, p["translation"].reshape(-1, 3), p["intrinsics"].reshape(-1, 3)

    # ------------------------------------------------------------------------------------------
    # Visibility (fixed within an LM round)
    # ------------------------------------------------------------------------------------------

    @torch.no_grad()
    def update_visibility(self, x: Tensor, min_facing: float = 0.0, exact: bool = True) -> Tensor:
        """Recompute which vertices each view sees (front-facing, not occluded, inside the image).

        Returns the ``(B, V, N)`` visibility; the normal term then uses the visible vertices of
        ``vertex_subset``. ``exact`` uses the triangle rasteriser's z-buffer, else the faster
        vertex splat (:func:`~facenormals.render.splat_zbuffer`).
        """
        _, verts, R, t, K = self._views(x, None)
        verts_v = verts[:, None].expand(-1, self.V, -1, -1).reshape(self.B * self.V, -1, 3)
        pixels, depth = project_points(verts_v, R, t, K)
        if exact:
            zbuffer = rasterize_depth(pixels, depth, self.model.faces, (self.H, self.W))
        else:
            zbuffer = splat_zbuffer(pixels, depth, (self.H, self.W))
        normals = vertex_normals(verts, self.model.faces)
        normals_v = normals[:, None].expand(-1, self.V, -1, -1).reshape(self.B * self.V, -1, 3)
        visible = visible_vertices(pixels, depth, normals_v @ R.transpose(1, 2), transform_points(verts_v, R, t),
                                   zbuffer, min_facing=min_facing).reshape(self.B, self.V, -1)
        self.set_visibility(visible)
        return visible

    @torch.no_grad()
    def set_visibility(self, visible: Tensor) -> None:
        """Use the vertices ``visible`` ``(B, V, N)`` (and in ``vertex_subset``) in the normal term.

        Stores the padded per-view vertex lists ``vis_index``, ``vis_valid`` ``(B, V, S)``, resets
        the robust weights (of vertices and landmarks) to 1, and builds each subject's ring structure.
        """
        subset = self.vertex_subset
        if subset is not None:
            if subset.shape not in ((self.N,), (self.B, self.N)) or subset.dtype != torch.bool:
                raise ValueError(f"vertex_subset: expected a bool tensor of shape (N,) or (B, N) = ({self.N},) or "
                                 f"({self.B}, {self.N}), got {subset.dtype} {tuple(subset.shape)}")
            subset = subset[:, None] if subset.dim() == 2 else subset
        used = visible & subset if subset is not None else visible
        counts = used.sum(-1)
        size = max(int(counts.max()), 1)
        self.vis_index = torch.argsort((~used).to(torch.uint8), dim=-1, stable=True)[..., :size]
        self.vis_valid = torch.arange(size, device=used.device) < counts[..., None]
        self.vertex_weights = torch.ones(self.B, self.V, size, dtype=self.dtype, device=used.device)
        self.landmark_weights = torch.ones(self.B, self.V, self.L, dtype=self.dtype, device=used.device)
        self._rings, self._slots = [], []
        for b in range(self.B):
            union = torch.nonzero(used[b].any(0)).squeeze(1)
            self._rings.append(Rings.build(self.model.faces, union, self.N))
            compact = torch.full((self.N,), -1, dtype=torch.long, device=used.device)
            compact[union] = torch.arange(union.shape[0], device=used.device)
            self._slots.append(torch.where(self.vis_valid[b], compact[self.vis_index[b]], -1))
        self._layouts: dict[tuple[int, ...] | None, _Layout] = {}
        self._cached: _Geometry | None = None

    def _all_is_none(self, index: Tensor | None) -> Tensor | None:
        """``None`` for all subjects (``index`` lists distinct subjects in ascending order)."""
        return None if index is None or index.shape[0] == self.B else index

    @staticmethod
    def _key(index: Tensor | None) -> tuple[int, ...] | None:
        return None if index is None else tuple(index.tolist())

    def _layout(self, index: Tensor | None) -> _Layout:
        """The ring and sparse-row structure of the subjects ``index``, built once per round."""
        key = self._key(index)
        if key in self._layouts:
            return self._layouts[key]
        ids = range(self.B) if key is None else key
        rings = Rings.cat([self._rings[b] for b in ids], self.N)
        slots, offset = [], 0
        for b in ids:
            slots.append(torch.where(self._slots[b] >= 0, self._slots[b] + offset, rings.num_slots))
            offset += self._rings[b].num_slots
        slot = torch.stack(slots)  # (K, V, S)
        count = slot.shape[0]
        vis_index = self._pick(self.vis_index, index)
        vertex = vis_index + self.N * torch.arange(count, device=slot.device)[:, None, None]
        rows = rings.row_structure(slot.reshape(-1), self.N)
        diagonal = torch.nonzero(rings.block_vertex[rows.block] == vertex.reshape(-1)[rows.entry]).squeeze(1)
        layout = _Layout(rings, slot, vertex, rows, rows.entry // slot.shape[-1], diagonal)
        self._layouts[key] = layout
        return layout

    @torch.no_grad()
    def update_robust_weights(self, x: Tensor, scale: float | None, landmark_scale: float | None = None) -> Tensor:
        r"""Robust weights of the normal and landmark residuals at ``x`` for iteratively reweighted least squares.

        Normals (Huber): a visible vertex whose normal residual has norm :math:`\rho > \delta`
        (``scale``) gets weight :math:`\delta / \rho`, so that its influence is that of Huber's loss;
        others keep weight 1. Vertices where the map is sampled poorly (silhouettes, holes, sub-pixel
        detail such as nostrils and ears) then stop biasing the fit.

        Landmarks (Cauchy): a landmark ``e`` pixels from its detection gets weight
        :math:`1 / (1 + (e / \delta_Z)^2)` (``landmark_scale`` = :math:`\delta_Z`). The loss
        redescends, so a wrongly detected landmark (a spurious peak tens of pixels off) is all but
        ignored instead of dragging the shape along, while landmarks within a pixel or two keep
        nearly full weight.

        ``None`` leaves a term's weights at 1. Returns the ``(B, V, S)`` vertex weights.
        """
        check_scale("scale", scale)
        check_scale("landmark_scale", landmark_scale)
        self.vertex_weights = torch.ones_like(self.vertex_weights)
        self.landmark_weights = torch.ones_like(self.landmark_weights)
        if scale is not None and self.weights.normals > 0:
            # (B, V, S, 3) without λN and the view weights, so that δ is in units of the normals
            scale_out = (self.weights.normals * self.view_weights).sqrt()
            r_n = self.residual_terms(x)[0] / torch.where(scale_out > 0, scale_out, 1.0)[..., None, None]
            self.vertex_weights = huber_weights(r_n.norm(dim=-1), scale)
        if landmark_scale is not None:
            error = self.landmark_errors(x).nan_to_num(0.0)
            self.landmark_weights = cauchy_weights(error, landmark_scale)
        return self.vertex_weights

    @torch.no_grad()
    def landmark_errors(self, x: Tensor) -> Tensor:
        """Pixel distance of each projected model landmark to its detection ``(B, V, L)``, NaN where absent."""
        g = self._geometry(x, None)
        error = (g.lm_uv - self.landmarks.reshape(self.B * self.V, self.L, 2)).norm(dim=-1).reshape(self.B, self.V, self.L)
        return torch.where(self.landmark_mask, error, torch.nan)

    # ------------------------------------------------------------------------------------------
    # Residuals
    # ------------------------------------------------------------------------------------------

    def _prior_rows(self, p: dict[str, Tensor], index: Tensor | None) -> list[Tensor]:
        w = self.weights
        rows = [prior_residuals(p["shape"], self.model.shape_std, weight=w.prior)]
        if self.E:
            rows.append(p["expression"] * w.expression_prior**0.5)
        if self.fit_intrinsics:
            prior, fitted = self._pick(self.intrinsics_prior, index), p["intrinsics"]
            focal = (fitted[..., :1].log() - prior[..., :1].log()) / w.focal_std  # log-normal focal prior
            centre = (fitted[..., 1:] - prior[..., 1:]) / w.center_std
            rows.append(torch.cat([focal, centre], dim=-1).reshape(prior.shape[0], -1))
        return rows

    def _prior_jacobian(self) -> Tensor:
        """The constant Jacobian ``(B, rows, P)`` of the prior rows."""
        w = self.weights
        rows = self.C + (3 * self.V if self.fit_intrinsics else 0)
        J = torch.zeros(self.B, rows, self.P, dtype=self.dtype, device=self.normal_maps.device)
        J[:, : self.K, : self.K] = torch.diag(w.prior**0.5 / self.model.shape_std)
        if self.E:
            J[:, self.K : self.C, self.K : self.C] = torch.eye(self.E, dtype=self.dtype) * w.expression_prior**0.5
        if self.fit_intrinsics:
            prior = self.intrinsics_prior
            for v in range(self.V):
                c0 = self.C + v * self.per_view + 6
                inv = torch.stack([torch.full_like(prior[:, v, 0], 1.0 / w.focal_std),
                                   torch.full_like(prior[:, v, 0], 1.0 / w.center_std),
                                   torch.full_like(prior[:, v, 0], 1.0 / w.center_std)], dim=-1)
                J[:, self.C + 3 * v : self.C + 3 * v + 3, c0 : c0 + 3] = torch.diag_embed(inv)
        return J

    def _row_weights(self, index: Tensor | None) -> Tensor:
        """sqrt of λN · view weight · robust weight, ``(KV, S)`` (0 on padding)."""
        w = self.weights.normals * self._pick(self.view_weights, index)[..., None] * self._pick(self.vertex_weights, index)
        w = w * self._pick(self.vis_valid, index)
        return w.sqrt().reshape(-1, w.shape[-1])

    def _geometry(self, x: Tensor, index: Tensor | None) -> "_Geometry":
        """Everything the residuals and the Jacobian share at ``x``; the last one is cached, since a
        solver asks for the Jacobian where it has just evaluated the residuals."""
        index = self._all_is_none(index)
        key = self._key(index)
        cached, plain = self._cached, _is_plain(x)
        if plain and cached is not None and cached.key == key and cached.x.shape == x.shape and torch.equal(cached.x, x):
            return cached
        if plain:  # the cached p and t are views of x: a caller's later in-place change must not reach them
            x = x.clone()
        p, verts, R, t, K = self._views(x, index)
        layout = self._layout(index)
        S = self.vis_index.shape[-1]
        flat = verts.reshape(-1, 3)
        face_geometry = layout.rings.face_geometry(flat)
        normals = torch.cat([layout.rings.normals(flat, face_geometry), flat.new_zeros(1, 3)])
        n_model = normals[layout.slot.reshape(-1, S)]  # (KV, S, 3)
        uv, _ = project_points(flat[layout.vertex.reshape(-1, S)], R, t, K)
        images = None if index is None else (index[:, None] * self.V + torch.arange(self.V, device=index.device)).reshape(-1)
        sampled, grad, inside = self._sampler.with_gradient(uv, images)
        support = self._support if images is None else self._support.index_select(0, images)
        lm = verts[:, None, self.lm_index].expand(-1, self.V, -1, -1).reshape(verts.shape[0] * self.V, self.L, 3)
        lm_uv, _ = project_points(lm, R, t, K)
        geometry = _Geometry(x, key, layout, p, verts, R, t, K, face_geometry, n_model, sampled, grad,
                             inside & _foreground_at(support, uv, (self.H, self.W)), lm, lm_uv)
        if plain:
            self._cached = geometry
        return geometry

    def residuals(self, x: Tensor, index: Tensor | None = None) -> Tensor:
        """All residuals ``(K, M)`` of the subjects ``index`` (default all); ``½‖r‖²`` is the energy."""
        return torch.cat(self.residual_terms(x, flat=True, index=index), dim=1)

    def residual_terms(self, x: Tensor, flat: bool = False, index: Tensor | None = None) -> list[Tensor]:
        """Residual blocks: ``[normals (K, V, S, 3), landmarks (K, V, L, 2)]`` then the priors."""
        index = self._all_is_none(index)
        g = self._geometry(x, index)
        count, S = x.shape[0], self.vis_index.shape[-1]
        n_cam = g.n_model @ g.R.transpose(1, 2)
        r_n = torch.where(g.valid[..., None], g.sampled - n_cam, 0.0) * self._row_weights(index)[..., None]
        views = count * self.V  # explicit sizes: a model may have no landmarks (L = 0)
        r_z = _landmark_differences(g.lm_uv, self._pick(self.landmarks, index).reshape(views, self.L, 2),
                                    self._pick(self.landmark_mask, index).reshape(views, self.L),
                                    math.sqrt(self.weights.landmarks))  # inputs checked by the constructor
        r_z = r_z * self._pick(self.landmark_weights, index).reshape(views, self.L, 1).sqrt()
        priors = self._prior_rows(g.p, index)
        if flat:
            return [r_n.reshape(count, -1), r_z.reshape(count, -1)] + priors
        return [r_n.reshape(count, self.V, S, 3), r_z.reshape(count, self.V, self.L, 2)] + priors

    # ------------------------------------------------------------------------------------------
    # Jacobian
    # ------------------------------------------------------------------------------------------

    def _view_columns(self, q: Tensor, R: Tensor, D: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """For model points ``q = p + t`` ``(KV, Q, 3)``: ``∂a/∂p`` ``(KV, Q, 2, 3)`` and
        ``∂a/∂(angles, t, intrinsics)`` ``(KV, Q, 2, per_view)``."""
        cam = q @ R.transpose(1, 2)
        P = projection_jacobian(cam, K)  # (KV, Q, 2, 3)
        PR = P @ R[:, None]
        parts = [P @ _rotated(D, q), PR]
        if self.fit_intrinsics:
            eye = torch.eye(2, dtype=q.dtype, device=q.device).expand(q.shape[0], q.shape[1], 2, 2)
            # d a / d log f = f * d a / d f = f * (x / z, y / z)
            focal = K[:, None, :1]
            parts.append(torch.cat([(focal * cam[..., :2] / cam[..., 2:3]).unsqueeze(-1), eye], dim=-1))
        return PR, torch.cat(parts, dim=-1)

    def _jacobian_parts(self, x: Tensor, dtype: torch.dtype, index: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The Jacobian's non-zero parts: normal rows' shape columns ``(K, V, 3S, C)`` and view
        columns ``(K, V, 3S, per_view)``, and the landmark and prior rows ``(K, 2VL + priors, P)``."""
        g = self._geometry(x, index)
        layout, R, t = g.layout, g.R, g.t
        count, V, S, L, C, pv = x.shape[0], self.V, self.vis_index.shape[-1], self.L, self.C, self.per_view
        D = euler_rotation_derivatives(g.p["angles"].reshape(-1, 3))  # (KV, 3, 3, 3)
        flat = g.verts.reshape(-1, 3)
        _, projector, raw = layout.rings.normal_derivatives(flat, g.face_geometry)

        # Normal rows: view columns densely, shape columns as one sparse product with the basis.
        PR, A_view = self._view_columns(flat[layout.vertex.reshape(-1, S)] + t[:, None], R, D, g.K)
        scale = self._row_weights(index) * g.valid.to(x.dtype)  # (KV, S)
        J_view = g.grad @ A_view  # ∇N ∂a/∂view, (KV, S, 3, per_view)
        J_view[..., 0:3] -= _rotated(D, g.n_model)
        J_view.mul_(scale[..., None, None])
        T = (g.grad @ PR).mul_(scale[..., None, None]).reshape(-1, 3, 3)  # ∇N ∂a/∂p, (KVS, 3, 3)
        projector = torch.cat([projector, projector.new_zeros(1, 3, 3)])[layout.slot.reshape(-1, S)]
        left = (R[:, None] @ projector).mul_(-scale[..., None, None]).reshape(-1, 3, 3)  # -R (I - n nᵀ)/|s|
        rows = layout.rows
        values = torch.bmm(left[rows.entry], raw[rows.block])
        values.index_add_(0, layout.diagonal, T[rows.entry[layout.diagonal]])
        # Into a fresh buffer: `csr @ dense` zero-fills and copies its result, ~1/3 of the product.
        shared = x.new_empty(rows.num_rows, C, dtype=dtype)
        torch.addmm(shared, rows.matrix(values.to(dtype), 3 * self.N), self._basis(dtype), beta=0.0, out=shared)

        # Landmark and prior rows.
        PR_lm, A_lm = self._view_columns(g.landmark_points + t[:, None], R, D, g.K)
        mask = self._pick(self.landmark_mask, index).to(x.dtype)
        lm_scale = self.weights.landmarks * mask * self._pick(self.landmark_weights, index)
        lm_scale = lm_scale.sqrt().reshape(count * V, L, 1, 1).to(x.dtype)
        J_lm = ((PR_lm * lm_scale) @ self.basis_landmarks).view(count, V, 2 * L, C)
        A_lm = (A_lm * lm_scale).view(count, V, 2 * L, pv)
        small = torch.zeros(count, V * 2 * L, self.P, dtype=dtype, device=x.device)
        for v in range(V):
            small[:, 2 * L * v : 2 * L * (v + 1), :C] = J_lm[:, v]
            small[:, 2 * L * v : 2 * L * (v + 1), C + v * pv : C + (v + 1) * pv] = A_lm[:, v]
        small = torch.cat([small, self._pick(self.prior_jacobian, index).to(dtype)], dim=1)
        return shared.view(count, V, 3 * S, C), J_view.to(dtype).view(count, V, 3 * S, pv), small

    def jacobian(self, x: Tensor, index: Tensor | None = None, *, dtype: torch.dtype | None = None) -> Tensor:
        """The analytic Jacobian ``(K, M, P)`` of :meth:`residuals`, formed in ``dtype`` (default: x's).

        ``(x, index)`` is :func:`~facenormals.optim.levenberg_marquardt`'s ``jacobian_fn`` call."""
        dtype = dtype or x.dtype
        shared, J_view, small = self._jacobian_parts(x, dtype, self._all_is_none(index))
        count, V, rows, C, pv = x.shape[0], self.V, shared.shape[2], self.C, self.per_view
        J = x.new_zeros(count, V * rows + small.shape[1], self.P, dtype=dtype)
        J[:, : V * rows, :C] = shared.reshape(count, V * rows, C)
        for v in range(V):
            J[:, v * rows : (v + 1) * rows, C + v * pv : C + (v + 1) * pv] = J_view[:, v]
        J[:, V * rows :] = small
        return J

    def normal_equations(self, x: Tensor, r: Tensor, index: Tensor | None = None, *,
                         dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
        """``JᵀJ`` ``(K, P, P)`` and ``Jᵀr`` ``(K, P)`` of :meth:`jacobian` and residuals ``r`` ``(K, M)``,
        formed in ``dtype`` without the Jacobian's zero blocks (for
        :func:`~facenormals.optim.levenberg_marquardt`'s ``normal_equations_fn``)."""
        dtype = dtype or x.dtype
        shared, J_view, small = self._jacobian_parts(x, dtype, self._all_is_none(index))
        count, V, rows, C, pv = x.shape[0], self.V, shared.shape[2], self.C, self.per_view
        r = r.to(dtype)
        r_views, r_small = r[:, : V * rows].view(count, V, 1, rows), r[:, V * rows :].unsqueeze(1)
        flat = shared.view(count, V * rows, C)
        H = small.transpose(1, 2) @ small
        H[:, :C, :C] += gram(flat)
        g = (r_small @ small).squeeze(1)
        g[:, :C] += (r[:, None, : V * rows] @ flat).squeeze(1)
        for v in range(V):
            cols = slice(C + v * pv, C + (v + 1) * pv)
            cross = J_view[:, v].transpose(1, 2) @ shared[:, v]  # (K, per_view, C); 2.5x faster than its transpose
            H[:, cols, :C] += cross
            H[:, :C, cols] += cross.transpose(1, 2)
            H[:, cols, cols] += J_view[:, v].transpose(1, 2) @ J_view[:, v]
            g[:, cols] += (r_views[:, v] @ J_view[:, v]).squeeze(1)
        return H, g

    def _basis(self, dtype: torch.dtype) -> Tensor:
        """The basis rows ``(3 N, C)`` in ``dtype`` (row ``3 i + j``: d X_ij / d (y, e)), cached on the model."""
        return self.model.basis_matrix(with_expression=bool(self.E), dtype=dtype)


@dataclass
class _Geometry:
    """The model and its projections at one ``x`` of the subjects ``key`` (see ``_geometry``)."""

    x: Tensor
    key: tuple[int, ...] | None
    layout: _Layout
    p: dict[str, Tensor]
    verts: Tensor  # (K, N, 3)
    R: Tensor  # (KV, 3, 3)
    t: Tensor  # (KV, 3)
    K: Tensor  # (KV, 3)
    face_geometry: tuple[Tensor, Tensor, Tensor]  # the ring faces' corners, unit normals and |c|
    n_model: Tensor  # (KV, S, 3) ring normals of the residual vertices, model frame
    sampled: Tensor  # (KV, S, 3) the maps at their projections
    grad: Tensor  # (KV, S, 3, 2) and the maps' derivatives there
    valid: Tensor  # (KV, S) inside the image and on the foreground
    landmark_points: Tensor  # (KV, L, 3)
    lm_uv: Tensor  # (KV, L, 2)


def _is_plain(x: Tensor) -> bool:
    """``x`` carries no autograd or ``torch.func`` state, so results computed from it may be reused."""
    return not (x.requires_grad or is_functorch_wrapped_tensor(x) or fwAD.unpack_dual(x).tangent is not None)


def _rotated(D: Tensor, q: Tensor) -> Tensor:
    """``out[..., :, j] = D_j q`` for rotation derivatives ``D`` ``(KV, 3, 3, 3)`` and points ``(KV, Q, 3)``."""
    out = q @ D.reshape(D.shape[0], 9, 3).transpose(1, 2)  # (KV, Q, 9): entry 3 j + k = (D_j q)_k
    return out.view(q.shape[0], q.shape[1], 3, 3).transpose(-1, -2)
