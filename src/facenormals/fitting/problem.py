r"""Residuals and analytic Jacobian of the paper's energy for B subjects seen in V views each.

Parameters of one subject, packed in this order:

- shape ``y`` (K), then expression ``e`` (E) if fitted;
- per view: ``(roll, pitch, yaw)``, ``t`` (3) and, if fitted, the intrinsics ``(f, u0, v0)``.

Residuals of one subject, per view: the normal term for the view's visible vertices (3 per vertex,
padded to a common count), the landmark term (2 per landmark); then the shape prior (K), an
expression prior if fitted, and an intrinsics prior per view if fitted. With
:math:`X = X_0 + W y + E e`, :math:`X_c = R (X + t)`, :math:`a = \pi_K(X_c)` and :math:`n_c = R\, n(X)`,
the normal residual is :math:`r = \sqrt{\lambda_N}\,(N(a) - n_c)` and its Jacobian

.. math::

    \frac{\partial r}{\partial \xi} = \sqrt{\lambda_N}\Big(\nabla N(a)\,\frac{\partial a}{\partial \xi}
    - \frac{\partial n_c}{\partial \xi}\Big),

with :math:`\nabla N` from :func:`~facenormals.sampling.sample_bicubic_with_gradient`,
:math:`\partial a / \partial X_c` from :func:`~facenormals.geometry.projection_jacobian` and
:math:`\partial n / \partial y` from :class:`~facenormals.mesh.VertexNormalsJacobian`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from facenormals.energy import landmark_residuals, normal_residuals, prior_residuals
from facenormals.energy.residuals import _foreground as map_foreground
from facenormals.geometry import (
    euler_rotation_derivatives,
    euler_to_rotation_matrix,
    project_points,
    projection_jacobian,
    transform_points,
)
from facenormals.mesh import VertexNormalsJacobian, vertex_normals
from facenormals.models import MorphableModel
from facenormals.render import rasterize_triangles, splat_zbuffer, visible_vertices
from facenormals.sampling import sample_bicubic_with_gradient

__all__ = ["FitWeights", "HeadFitProblem"]


@dataclass(frozen=True)
class FitWeights:
    """Weights of the energy terms (the paper's defaults) and of the extra priors.

    Attributes:
        normals: λN of EN.
        landmarks: λZ of EZ.
        prior: λP of the shape prior EP.
        expression_prior: weight of ½‖e‖² when expressions are fitted.
        focal_std: relative standard deviation of the focal-length prior, ``σ_f / f_prior``.
        center_std: standard deviation of the principal-point prior, pixels.
    """

    normals: float = 1.0
    landmarks: float = 0.8
    prior: float = 0.4
    expression_prior: float = 1.0
    focal_std: float = 0.2
    center_std: float = 4.0


class HeadFitProblem:
    """The fitting energy of ``B`` subjects with ``V`` views each, for :func:`levenberg_marquardt`.

    Args:
        model: the morphable model (its dtype is the problem's dtype).
        normal_maps: ``(B, V, 3, H, W)`` camera-frame normal maps, zero on background.
        landmarks: ``(B, V, L, 2)`` detected landmarks of the model's landmark list, pixels.
        landmark_mask: ``(B, V, L)`` which landmarks are present.
        intrinsics_prior: ``(B, V, 3)`` prior ``(f, u0, v0)``; also the fixed intrinsics when they
            are not fitted.
        weights: the :class:`FitWeights`.
        fit_intrinsics: fit ``(f, u0, v0)`` per view.
        fit_expression: fit expression coefficients (shared by the views).
        view_weights: ``(B, V)`` extra weight of each view's normal term (e.g. 0 for a view whose
            map has no foreground).
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
    ) -> None:
        self.model = model
        self.B, self.V = normal_maps.shape[:2]
        self.H, self.W = normal_maps.shape[-2:]
        self.K = model.num_shape
        self.E = model.num_expressions if fit_expression else 0
        self.fit_intrinsics = fit_intrinsics
        self.per_view = 9 if fit_intrinsics else 6
        self.P = self.K + self.E + self.V * self.per_view
        self.dtype = model.mean.dtype
        self.normal_maps = normal_maps.to(self.dtype)
        self.landmarks = landmarks.to(self.dtype)
        self.landmark_mask = landmark_mask
        self.intrinsics_prior = intrinsics_prior.to(self.dtype)
        self.weights = weights
        ones = torch.ones(self.B, self.V, dtype=self.dtype, device=normal_maps.device)
        self.view_weights = ones if view_weights is None else view_weights.to(self.dtype)
        self.normals_jacobian = VertexNormalsJacobian(model.faces, model.shape_basis)
        self.expression_jacobian = (
            VertexNormalsJacobian(model.faces, model.expression_basis) if self.E else None
        )
        self.W_basis = model.shape_basis.permute(1, 2, 0).contiguous()  # (N, 3, K)
        self.E_basis = model.expression_basis.permute(1, 2, 0).contiguous() if self.E else None
        self.lm_index = model.landmark_indices
        basis = self.W_basis if not self.E else torch.cat([self.W_basis, self.E_basis], dim=-1)
        self.basis_landmarks = basis[self.lm_index]  # (L, 3, C)
        self.vis_index = torch.zeros(self.B, self.V, 1, dtype=torch.long, device=normal_maps.device)
        self.vis_valid = torch.zeros(self.B, self.V, 1, dtype=torch.bool, device=normal_maps.device)
        self.vertex_weights = torch.ones(self.B, self.V, 1, dtype=self.dtype, device=normal_maps.device)

    # ------------------------------------------------------------------------------------------
    # Parameters
    # ------------------------------------------------------------------------------------------

    def pack(self, shape: Tensor, angles: Tensor, translation: Tensor, intrinsics: Tensor,
             expression: Tensor | None = None) -> Tensor:
        """Parameters ``(B, P)`` from shape ``(B, K)``, per-view angles, translations, intrinsics ``(B, V, 3)``."""
        parts = [shape]
        if self.E:
            parts.append(expression if expression is not None else shape.new_zeros(self.B, self.E))
        view = [angles, translation] + ([intrinsics] if self.fit_intrinsics else [])
        parts.append(torch.cat(view, dim=-1).reshape(self.B, -1))
        return torch.cat(parts, dim=1)

    def unpack(self, x: Tensor) -> dict[str, Tensor]:
        """The named parameters of ``x`` ``(B, P)``."""
        out = {"shape": x[:, : self.K]}
        out["expression"] = x[:, self.K : self.K + self.E] if self.E else None
        views = x[:, self.K + self.E :].reshape(self.B, self.V, self.per_view)
        out["angles"], out["translation"] = views[..., 0:3], views[..., 3:6]
        out["intrinsics"] = views[..., 6:9] if self.fit_intrinsics else self.intrinsics_prior
        return out

    def vertices(self, x: Tensor) -> Tensor:
        p = self.unpack(x)
        return self.model(p["shape"], p["expression"]) if self.E else self.model(p["shape"])

    def _views(self, x: Tensor):
        """Per (subject, view) flattened: vertices (BV, N, 3), R (BV, 3, 3), t (BV, 3), K (BV, 3)."""
        p = self.unpack(x)
        verts = self.vertices(x)
        R = euler_to_rotation_matrix(p["angles"].reshape(-1, 3))
        t = p["translation"].reshape(-1, 3)
        K = p["intrinsics"].reshape(-1, 3)
        verts_v = verts[:, None].expand(-1, self.V, -1, -1).reshape(self.B * self.V, -1, 3)
        return p, verts, verts_v, R, t, K

    # ------------------------------------------------------------------------------------------
    # Visibility (fixed within an LM round)
    # ------------------------------------------------------------------------------------------

    @torch.no_grad()
    def update_visibility(self, x: Tensor, min_facing: float = 0.0, exact: bool = True) -> Tensor:
        """Recompute which vertices each view sees (front-facing, not occluded, inside the image).

        Returns the ``(B, V, N)`` visibility and stores the padded visible indices used by the residuals.
        ``exact`` uses the triangle rasteriser's z-buffer, else the faster vertex splat
        (:func:`~facenormals.render.splat_zbuffer`).
        """
        _, verts, verts_v, R, t, K = self._views(x)
        pixels, depth = project_points(verts_v, R, t, K)
        if exact:
            zbuffer = rasterize_triangles(pixels, depth, self.model.faces, (self.H, self.W)).depth
        else:
            zbuffer = splat_zbuffer(pixels, depth, (self.H, self.W))
        normals = vertex_normals(verts, self.model.faces)
        normals_v = normals[:, None].expand(-1, self.V, -1, -1).reshape(self.B * self.V, -1, 3)
        camera_normals = normals_v @ R.transpose(1, 2)
        visible = visible_vertices(pixels, depth, camera_normals, transform_points(verts_v, R, t), zbuffer,
                                   min_facing=min_facing)
        counts = visible.sum(1)
        size = max(int(counts.max()), 1)
        order = torch.argsort((~visible).to(torch.uint8), dim=1, stable=True)[:, :size]
        self.vis_index = order.reshape(self.B, self.V, size)
        self.vis_valid = (torch.arange(size, device=x.device)[None] < counts[:, None]).reshape(self.B, self.V, size)
        self.vertex_weights = torch.ones(self.B, self.V, size, dtype=self.dtype, device=x.device)
        # Per-round caches of the Jacobian: per subject, the union of its views' visible vertices and
        # the normal-Jacobian restricted to it, and the basis rows of each view's visible vertices.
        per_subject = visible.reshape(self.B, self.V, -1).any(1)  # (B, N)
        self.vis_compact = torch.zeros_like(self.vis_index)
        self.normals_subsets, self.expression_subsets = [], []
        for b in range(self.B):
            union = per_subject[b].clone()
            union[0] |= not bool(union.any())  # keep the caches non-empty when nothing is visible
            union_index = torch.nonzero(union).squeeze(1)
            compact = torch.zeros(union.shape[0], dtype=torch.long, device=x.device)
            compact[union_index] = torch.arange(union_index.shape[0], device=x.device)
            self.vis_compact[b] = compact[self.vis_index[b]]
            self.normals_subsets.append(self.normals_jacobian.subset(union_index))
            if self.E:
                self.expression_subsets.append(self.expression_jacobian.subset(union_index))
        basis = self.W_basis if not self.E else torch.cat([self.W_basis, self.E_basis], dim=-1)
        self.basis_visible = basis[self.vis_index.reshape(self.B * self.V, size)]  # (BV, S, 3, C)
        return visible.reshape(self.B, self.V, -1)

    @torch.no_grad()
    def update_robust_weights(self, x: Tensor, scale: float) -> Tensor:
        r"""Huber weights of the normal residuals at ``x`` for iteratively reweighted least squares.

        A visible vertex whose normal residual has norm :math:`\rho > \delta` (``scale``) gets weight
        :math:`\delta / \rho`, so that its influence is that of Huber's loss; others keep weight 1.
        Vertices where the map is sampled poorly (silhouettes, holes, sub-pixel detail such as
        nostrils and ears) then stop biasing the fit. Returns the ``(B, V, S)`` weights.
        """
        self.vertex_weights = torch.ones_like(self.vertex_weights)
        r_n = self.residual_terms(x)[0] / self.weights.normals**0.5  # (B, V, S, 3), unweighted
        rho = r_n.norm(dim=-1)
        self.vertex_weights = torch.where(rho > scale, scale / rho.clamp_min(1e-12), torch.ones_like(rho))
        return self.vertex_weights

    # ------------------------------------------------------------------------------------------
    # Residuals
    # ------------------------------------------------------------------------------------------

    def _prior_rows(self, p: dict[str, Tensor]) -> list[Tensor]:
        w = self.weights
        rows = [prior_residuals(p["shape"], self.model.shape_std, weight=w.prior)]
        if self.E:
            rows.append(p["expression"] * w.expression_prior**0.5)
        if self.fit_intrinsics:
            prior = self.intrinsics_prior
            scale = torch.stack(
                [prior[..., 0] * w.focal_std, torch.full_like(prior[..., 0], w.center_std),
                 torch.full_like(prior[..., 0], w.center_std)], dim=-1)
            rows.append(((p["intrinsics"] - prior) / scale).reshape(self.B, -1))
        return rows

    def residuals(self, x: Tensor) -> Tensor:
        """All residuals ``(B, M)``; ``½‖r‖²`` is the weighted energy."""
        return torch.cat(self.residual_terms(x, flat=True), dim=1)

    def residual_terms(self, x: Tensor, flat: bool = False) -> list[Tensor]:
        """Residual blocks: per view ``[normals (B, V, S, 3), landmarks (B, V, L, 2)]`` then priors."""
        p, verts, verts_v, R, t, K = self._views(x)
        BV, S = self.B * self.V, self.vis_index.shape[-1]
        index = self.vis_index.reshape(BV, S)
        pts = torch.gather(verts_v, 1, index[..., None].expand(-1, -1, 3))
        normals = vertex_normals(verts, self.model.faces)
        normals_v = normals[:, None].expand(-1, self.V, -1, -1).reshape(BV, -1, 3)
        n_vis = torch.gather(normals_v, 1, index[..., None].expand(-1, -1, 3)) @ R.transpose(1, 2)
        uv, _ = project_points(pts, R, t, K)
        maps = self.normal_maps.reshape(BV, 3, self.H, self.W)
        r_n, _ = normal_residuals(maps, uv, n_vis, self.vis_valid.reshape(BV, S), weight=self.weights.normals)
        r_n = r_n * (self.view_weights.reshape(BV, 1) * self.vertex_weights.reshape(BV, S)).sqrt()[..., None]
        uv_lm, _ = project_points(verts_v[:, self.lm_index], R, t, K)
        r_z = landmark_residuals(
            uv_lm, self.landmarks.reshape(BV, -1, 2), self.landmark_mask.reshape(BV, -1), weight=self.weights.landmarks
        )
        views = torch.cat([r_n.reshape(self.B, self.V, -1), r_z.reshape(self.B, self.V, -1)], dim=-1)
        blocks = [views.reshape(self.B, -1)] + self._prior_rows(p)
        if flat:
            return blocks
        return [r_n.reshape(self.B, self.V, S, 3), r_z.reshape(self.B, self.V, -1, 2)] + blocks[1:]

    # ------------------------------------------------------------------------------------------
    # Jacobian
    # ------------------------------------------------------------------------------------------

    def jacobian(self, x: Tensor, dtype: torch.dtype | None = None) -> Tensor:
        """The analytic Jacobian ``(B, M, P)`` of :meth:`residuals`, formed in ``dtype`` (default: x's)."""
        dtype = dtype or x.dtype
        p, verts, verts_v, R, t, K = self._views(x)
        B, V, Kdim, E = self.B, self.V, self.K, self.E
        BV, S = B * V, self.vis_index.shape[-1]
        L = self.lm_index.shape[0]
        index = self.vis_index.reshape(BV, S)
        angles = p["angles"].reshape(BV, 3)
        D = euler_rotation_derivatives(angles)  # (BV, 3, 3, 3)

        # per subject: the union of its visible vertices, (U_b, 3) normals and (U_b, 3, C) derivatives
        normals_u, d_normals = [], []
        for b in range(B):
            n_b, dn_b = self.normals_subsets[b](verts[b : b + 1])
            if E:
                dn_b = torch.cat([dn_b, self.expression_subsets[b](verts[b : b + 1])[1]], dim=-1)
            normals_u.append(n_b[0])
            d_normals.append(dn_b[0])
        C = Kdim + E

        def view_rows(point_index: Tensor, with_normals: bool, Wq: Tensor):
            """dr/d(shared, view) for points ``point_index`` (BV, Q) with basis rows ``Wq`` (BV, Q, 3, C)."""
            Q = point_index.shape[1]
            q = torch.gather(verts_v, 1, point_index[..., None].expand(-1, -1, 3)) + t[:, None]  # p + t
            cam = q @ R.transpose(1, 2)
            P = projection_jacobian(cam, K)  # (BV, Q, 2, 3)
            PR = (P.unsqueeze(-1) * R[:, None, None]).sum(-2)  # (BV, Q, 2, 3)
            A_shared = PR[..., 0:1] * Wq[:, :, None, 0]
            A_shared.addcmul_(PR[..., 1:2], Wq[:, :, None, 1]).addcmul_(PR[..., 2:3], Wq[:, :, None, 2])
            DQ = torch.einsum("bjkl,bnl->bnkj", D, q)  # (BV, Q, 3, 3)
            A_angles = (P.unsqueeze(-1) * DQ.unsqueeze(-3)).sum(-2)  # (BV, Q, 2, 3)
            A_view = [A_angles, PR]
            if self.fit_intrinsics:
                z = cam[..., 2:3]
                d_f = cam[..., :2] / z  # (BV, Q, 2)
                eye = torch.eye(2, dtype=x.dtype, device=x.device).expand(BV, Q, 2, 2)
                A_view.append(torch.cat([d_f.unsqueeze(-1), eye], dim=-1))
            A_view = torch.cat(A_view, dim=-1)  # (BV, Q, 2, per_view)
            if not with_normals:
                return A_shared, A_view, None, None, None
            compact = self.vis_compact.reshape(BV, -1)
            # per (subject, view) row selection; index_select is several times faster than
            # broadcast advanced indexing on these (U, 3, C) blocks
            dn = torch.stack([d_normals[i // V].index_select(0, compact[i]) for i in range(BV)])  # (BV, Q, 3, C)
            n_q = torch.stack([normals_u[i // V].index_select(0, compact[i]) for i in range(BV)])  # (BV, Q, 3)
            Rdn = R[:, None, :, 0, None] * dn[:, :, None, 0]  # (BV, Q, 3, C) = R @ dn
            Rdn.addcmul_(R[:, None, :, 1, None], dn[:, :, None, 1]).addcmul_(R[:, None, :, 2, None], dn[:, :, None, 2])
            Dn = torch.einsum("bjkl,bnl->bnkj", D, n_q)  # (BV, Q, 3, 3): d n_c / d angle_j
            return A_shared, A_view, Rdn, Dn, n_q

        # Normal rows.
        A_shared, A_view, Rdn, Dn, n_vis = view_rows(index, True, self.basis_visible)
        pts_uv, _ = project_points(torch.gather(verts_v, 1, index[..., None].expand(-1, -1, 3)), R, t, K)
        maps = self.normal_maps.reshape(BV, 3, self.H, self.W)
        _, grad, inside = sample_bicubic_with_gradient(maps, pts_uv)  # grad (BV, S, 3, 2)
        # the rows normal_residuals keeps: visible, inside the image, on the map's foreground
        valid = self.vis_valid.reshape(BV, S) & inside & map_foreground(maps, pts_uv)
        scale = (self.weights.normals * self.view_weights.reshape(BV, 1) * self.vertex_weights.reshape(BV, S)).sqrt()
        scale = scale * valid.to(x.dtype)  # (BV, S)

        def times_grad(A: Tensor) -> Tensor:  # ∇N (BV, S, 3, 2) @ A (BV, S, 2, D) without tiny matmuls
            out = grad[..., 0:1] * A[:, :, None, 0]
            return out.addcmul_(grad[..., 1:2], A[:, :, None, 1])

        J_n_shared = times_grad(A_shared).sub_(Rdn).mul_(scale[..., None, None])  # (BV, S, 3, C)
        J_n_view = times_grad(A_view)
        J_n_view[..., 0:3] -= Dn
        J_n_view.mul_(scale[..., None, None])  # (BV, S, 3, per_view)

        # Landmark rows.
        lm_index = self.lm_index[None].expand(BV, -1)
        A_lm_shared, A_lm_view, _, _, _ = view_rows(lm_index, False, self.basis_landmarks[None].expand(BV, -1, -1, -1))
        lm_scale = self.weights.landmarks**0.5 * self.landmark_mask.reshape(BV, L).to(x.dtype)
        J_z_shared = A_lm_shared * lm_scale[..., None, None]
        J_z_view = A_lm_view * lm_scale[..., None, None]

        rows_per_view = 3 * S + 2 * L
        prior_rows = Kdim + E + (3 * V if self.fit_intrinsics else 0)
        J = torch.zeros(B, V * rows_per_view + prior_rows, self.P, dtype=dtype, device=x.device)
        J_n_shared, J_n_view = J_n_shared.view(B, V, S, 3, C), J_n_view.view(B, V, S, 3, self.per_view)
        J_z_shared, J_z_view = J_z_shared.view(B, V, L, 2, C), J_z_view.view(B, V, L, 2, self.per_view)
        for v in range(V):
            sel = (slice(None), v)
            r0 = v * rows_per_view
            c0 = Kdim + E + v * self.per_view
            block = J[:, r0 : r0 + 3 * S]
            block[..., :C] = J_n_shared[sel].reshape(B, 3 * S, C)
            block[..., c0 : c0 + self.per_view] = J_n_view[sel].reshape(B, 3 * S, self.per_view)
            block = J[:, r0 + 3 * S : r0 + rows_per_view]
            block[..., :C] = J_z_shared[sel].reshape(B, 2 * L, C)
            block[..., c0 : c0 + self.per_view] = J_z_view[sel].reshape(B, 2 * L, self.per_view)
        r0 = V * rows_per_view
        w = self.weights
        J[:, r0 : r0 + Kdim, :Kdim] = torch.diag(w.prior**0.5 / self.model.shape_std).to(dtype)
        r0 += Kdim
        if E:
            J[:, r0 : r0 + E, Kdim : Kdim + E] = torch.eye(E, dtype=dtype) * w.expression_prior**0.5
            r0 += E
        if self.fit_intrinsics:
            prior = self.intrinsics_prior
            for v in range(V):
                c0 = Kdim + E + v * self.per_view + 6
                inv = torch.stack([1.0 / (prior[:, v, 0] * w.focal_std),
                                   torch.full_like(prior[:, v, 0], 1.0 / w.center_std),
                                   torch.full_like(prior[:, v, 0], 1.0 / w.center_std)], dim=-1)
                J[:, r0 + 3 * v : r0 + 3 * v + 3, c0 : c0 + 3] = torch.diag_embed(inv).to(dtype)
        return J
