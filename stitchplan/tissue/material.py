"""Hyperelastic plane-strain materials: PK2 stress and consistent material tangent.

Arrays are points-first: F, E, S are (n, 2, 2); the material tangent dS/dE is (n, 2, 2, 2, 2).
Plane strain: F_33 = 1, so the in-plane right Cauchy-Green tensor carries all the strain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Material

IDENTITY = np.eye(2)


def matmul22(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b for stacks of 2 x 2 matrices, (n, 2, 2); written out by components because
    numpy's batched matmul is slow for matrices this small."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0, 0] = a[:, 0, 0] * b[:, 0, 0] + a[:, 0, 1] * b[:, 1, 0]
    out[:, 0, 1] = a[:, 0, 0] * b[:, 0, 1] + a[:, 0, 1] * b[:, 1, 1]
    out[:, 1, 0] = a[:, 1, 0] * b[:, 0, 0] + a[:, 1, 1] * b[:, 1, 0]
    out[:, 1, 1] = a[:, 1, 0] * b[:, 0, 1] + a[:, 1, 1] * b[:, 1, 1]
    return out


def green_lagrange_strain(deformation_gradient: np.ndarray) -> np.ndarray:
    """E = (F^T F - I) / 2."""
    return 0.5 * (matmul22(deformation_gradient.transpose(0, 2, 1), deformation_gradient) - IDENTITY)


@dataclass(frozen=True)
class SaintVenantKirchhoff:
    """W(E) = lambda/2 (tr E)^2 + mu tr(E^2) (eq. 3.3); S = lambda tr(E) I + 2 mu E (eq. A.1)."""

    lame_lambda: float
    lame_mu: float

    def energy(self, deformation_gradient: np.ndarray) -> np.ndarray:
        strain = green_lagrange_strain(deformation_gradient)
        trace = np.trace(strain, axis1=1, axis2=2)
        return 0.5 * self.lame_lambda * trace**2 + self.lame_mu * np.einsum("nij,nij->n", strain, strain)

    def pk2_stress(self, deformation_gradient: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Returns S (n, 2, 2) and dS/dE (n, 2, 2, 2, 2)."""
        strain = green_lagrange_strain(deformation_gradient)
        stress = 2.0 * self.lame_mu * strain
        trace = self.lame_lambda * (strain[:, 0, 0] + strain[:, 1, 1])
        stress[:, 0, 0] += trace
        stress[:, 1, 1] += trace
        i = IDENTITY
        tangent = self.lame_lambda * np.einsum("ij,kl->ijkl", i, i) + self.lame_mu * (
            np.einsum("ik,jl->ijkl", i, i) + np.einsum("il,jk->ijkl", i, i)
        )
        return stress, np.broadcast_to(tangent, (len(stress), 2, 2, 2, 2))


@dataclass(frozen=True)
class NeoHookean:
    """Compressible neo-Hookean: W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2.

    S = mu (I - C^-1) + lambda ln J C^-1, dS/dE = lambda C^-1 x C^-1 + 2 (mu - lambda ln J) I_{C^-1}.
    """

    lame_lambda: float
    lame_mu: float

    def energy(self, deformation_gradient: np.ndarray) -> np.ndarray:
        j = determinant(deformation_gradient)
        i1 = np.einsum("nij,nij->n", deformation_gradient, deformation_gradient) + 1.0
        log_j = np.log(j)
        return 0.5 * self.lame_mu * (i1 - 3.0) - self.lame_mu * log_j + 0.5 * self.lame_lambda * log_j**2

    def pk2_stress(self, deformation_gradient: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        right_cauchy_green = matmul22(deformation_gradient.transpose(0, 2, 1), deformation_gradient)
        c_inv = np.linalg.inv(right_cauchy_green)
        log_j = np.log(determinant(deformation_gradient))
        stress = self.lame_mu * (IDENTITY - c_inv) + self.lame_lambda * log_j[:, None, None] * c_inv
        coefficient = (self.lame_mu - self.lame_lambda * log_j)[:, None, None, None, None]
        tangent = self.lame_lambda * np.einsum("nij,nkl->nijkl", c_inv, c_inv) + coefficient * (
            np.einsum("nik,njl->nijkl", c_inv, c_inv) + np.einsum("nil,njk->nijkl", c_inv, c_inv)
        )
        return stress, tangent


def first_piola(model: SaintVenantKirchhoff | NeoHookean | PointwiseMaterial,
                deformation_gradient: np.ndarray) -> np.ndarray:
    """P = F S (n, 2, 2) alone, written out by components: the residual needs no tangent,
    and this is ~3x cheaper than pk2_stress and a product (tests/test_material.py)."""
    if isinstance(model, PointwiseMaterial):
        return model.per_part(first_piola, deformation_gradient)
    f = deformation_gradient
    f00, f01, f10, f11 = f[:, 0, 0], f[:, 0, 1], f[:, 1, 0], f[:, 1, 1]
    c00, c01, c11 = f00 * f00 + f10 * f10, f00 * f01 + f10 * f11, f01 * f01 + f11 * f11  # C = F^T F
    lam, mu = model.lame_lambda, model.lame_mu
    if isinstance(model, SaintVenantKirchhoff):
        trace = 0.5 * lam * (c00 + c11 - 2.0)
        s00, s01, s11 = mu * (c00 - 1.0) + trace, mu * c01, mu * (c11 - 1.0) + trace
    else:
        j = f00 * f11 - f01 * f10
        scale = (lam * np.log(j) - mu) / (j * j)  # (lambda ln J - mu) / det C
        s00, s01, s11 = mu + scale * c11, -scale * c01, mu + scale * c00
    out = np.empty_like(f)
    out[:, 0, 0] = f00 * s00 + f01 * s01
    out[:, 0, 1] = f00 * s01 + f01 * s11
    out[:, 1, 0] = f10 * s00 + f11 * s01
    out[:, 1, 1] = f10 * s01 + f11 * s11
    return out


def determinant(deformation_gradient: np.ndarray) -> np.ndarray:
    """det F of (n, 2, 2) in closed form (np.linalg.det is ~10x slower for 2 x 2)."""
    f = deformation_gradient
    return f[:, 0, 0] * f[:, 1, 1] - f[:, 0, 1] * f[:, 1, 0]


def lame_at_rest(model: SaintVenantKirchhoff | NeoHookean | PointwiseMaterial,
                 n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """lambda and mu per point, (n,) each: at F = I both materials' tangent A = dP/dF is the
    isotropic linear-elastic one, lambda d_iJ d_kL + mu (d_ik d_JL + d_iL d_Jk)."""
    if isinstance(model, PointwiseMaterial):
        index = model.checked_index(n_points)
        return (np.array([part.lame_lambda for part in model.parts])[index],
                np.array([part.lame_mu for part in model.parts])[index])
    return np.full(n_points, model.lame_lambda), np.full(n_points, model.lame_mu)


def make_material(material: Material) -> SaintVenantKirchhoff | NeoHookean:
    cls = SaintVenantKirchhoff if material.model == "saint-venant-kirchhoff" else NeoHookean
    return cls(material.lame_lambda, material.lame_mu)


@dataclass(frozen=True, eq=False)
class PointwiseMaterial:
    """A material per quadrature point (material regions): point q follows parts[index[q]].
    Its stresses are asked for at every quadrature point at once, in their order."""

    parts: tuple  # SaintVenantKirchhoff | NeoHookean
    index: np.ndarray  # (nq,) into parts

    def checked_index(self, count: int) -> np.ndarray:
        """`index`, after checking that it is asked for at its own `count` points."""
        if count != len(self.index):
            raise ValueError(f"a pointwise material holds {len(self.index)} points, asked at {count}")
        return self.index

    def _groups(self, count: int):
        index = self.checked_index(count)
        for k, part in enumerate(self.parts):
            selected = np.flatnonzero(index == k)
            if len(selected):
                yield part, selected

    def per_part(self, function, deformation_gradient: np.ndarray):
        """function(part, F) on each part's points, scattered back into point order: an array,
        or a tuple of arrays for a function that returns a tuple."""
        n = len(deformation_gradient)
        outputs, single = None, True
        for part, selected in self._groups(n):
            result = function(part, deformation_gradient[selected])
            single = not isinstance(result, tuple)
            pieces = (result,) if single else result
            if outputs is None:
                outputs = [np.empty((n, *piece.shape[1:])) for piece in pieces]
            for out, piece in zip(outputs, pieces):
                out[selected] = piece
        return outputs[0] if single else tuple(outputs)

    def energy(self, deformation_gradient: np.ndarray) -> np.ndarray:
        return self.per_part(lambda part, f: part.energy(f), deformation_gradient)

    def pk2_stress(self, deformation_gradient: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.per_part(lambda part, f: part.pk2_stress(f), deformation_gradient)


def first_piola_and_tangent(
    model: SaintVenantKirchhoff | NeoHookean, deformation_gradient: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """P = F S and A = dP/dF (eq. 3.13-3.16: A_iJkL = delta_ik S_JL + F_iM C_MJNL F_kN).

    Returns P (n, 2, 2) and A (n, 2, 2, 2, 2) indexed [n, i, J, k, L].
    """
    if isinstance(model, PointwiseMaterial):
        return model.per_part(first_piola_and_tangent, deformation_gradient)
    stress, tangent = model.pk2_stress(deformation_gradient)
    n = len(stress)
    first_piola = matmul22(deformation_gradient, stress)
    if isinstance(model, SaintVenantKirchhoff):
        # F C F for C = lambda I x I + 2 mu I_sym, in closed form:
        # lambda F_iJ F_kL + mu (F F^T)_ik delta_JL + mu F_iL F_kJ
        f = deformation_gradient
        eye = np.eye(2)
        ffT = f @ f.transpose(0, 2, 1)
        material = (model.lame_lambda * f[:, :, :, None, None] * f[:, None, None, :, :]
                    + model.lame_mu * ffT[:, :, None, :, None] * eye[None, None, :, None, :]
                    + model.lame_mu * f[:, :, None, None, :] * f[:, None, :, :, None].transpose(0, 1, 3, 2, 4))
        material += eye[None, :, None, :, None] * stress[:, None, :, None, :]  # D_ijlm, eq. 3.14
        return first_piola, material
    # F_iM C_MJNL -> (n, i, J N L); then contract N with F_kN
    left = (deformation_gradient @ tangent.reshape(-1, 2, 8)).reshape(n, 2, 2, 2, 2)
    material = np.einsum("niJNL,nkN->niJkL", left, deformation_gradient, optimize=True)
    material += np.eye(2)[None, :, None, :, None] * stress[:, None, :, None, :]  # D_ijlm, eq. 3.14
    return first_piola, material
