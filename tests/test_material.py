"""Hyperelastic laws: stresses are derivatives of the energy and tangents are derivatives of
the stresses, checked by central finite differences at random admissible F (det F > 0)."""

from __future__ import annotations

import numpy as np
import pytest

from stitchplan.tissue.material import (
    NeoHookean,
    SaintVenantKirchhoff,
    first_piola,
    first_piola_and_tangent,
    green_lagrange_strain,
)

MATERIALS = [
    pytest.param(SaintVenantKirchhoff(lame_lambda=0.8, lame_mu=0.3), id="svk"),
    pytest.param(NeoHookean(lame_lambda=0.8, lame_mu=0.3), id="neo-hookean"),
    pytest.param(SaintVenantKirchhoff(lame_lambda=0.189151, lame_mu=0.147688), id="svk-phantom"),
    pytest.param(NeoHookean(lame_lambda=0.189151, lame_mu=0.147688), id="neo-hookean-phantom"),
]
STEP = 1e-6  # central differences: truncation ~STEP^2, cancellation ~1e-16/STEP
FD_RTOL = 1e-6  # relative to the largest entry; observed ~1e-10


@pytest.fixture
def deformation_gradients(rng) -> np.ndarray:
    """(n, 2, 2): random moderate F, a 60 % stretch with 30 % compression, and a rotated shear."""
    random = np.eye(2) + 0.3 * rng.standard_normal((40, 2, 2))
    random = random[np.linalg.det(random) > 0.3]
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    large = np.array([np.diag([1.6, 0.7]), rotation @ np.array([[1.0, 0.4], [0.0, 1.1]])])
    gradients = np.concatenate([random, large])
    assert len(gradients) >= 20 and np.all(np.linalg.det(gradients) > 0)
    return gradients


def unit(k: int, l: int) -> np.ndarray:
    e = np.zeros((2, 2))
    e[k, l] = 1.0
    return e


def symmetric_unit(k: int, l: int) -> np.ndarray:
    """dE with dE_kl = dE_lk and sum = 1 on the pair, so d f / d E_kl = (f(E + h e) - f(E - h e)) / 2h
    for any f of a symmetric E whose derivative has minor symmetry."""
    return 0.5 * (unit(k, l) + unit(l, k))


def stretch_from_strain(strain: np.ndarray) -> np.ndarray:
    """U = (I + 2 E)^(1/2), (n, 2, 2): the symmetric F with Green-Lagrange strain E."""
    values, vectors = np.linalg.eigh(np.eye(2) + 2.0 * strain)
    return np.einsum("nik,nk,njk->nij", vectors, np.sqrt(values), vectors)


@pytest.mark.parametrize("material", MATERIALS)
def test_first_piola_is_the_energy_derivative(material, deformation_gradients):
    """P_iJ = dW / dF_iJ."""
    first_piola, _ = first_piola_and_tangent(material, deformation_gradients)
    finite_difference = np.zeros_like(first_piola)
    for i in range(2):
        for j in range(2):
            step = STEP * unit(i, j)
            finite_difference[:, i, j] = (material.energy(deformation_gradients + step)
                                          - material.energy(deformation_gradients - step)) / (2 * STEP)
    np.testing.assert_allclose(first_piola, finite_difference, rtol=0,
                               atol=FD_RTOL * np.abs(first_piola).max())


@pytest.mark.parametrize("material", MATERIALS)
def test_residual_first_piola_matches_the_one_with_its_tangent(material, deformation_gradients):
    """The residual's closed-form P = F S (no tangent) equals the P computed with the tangent."""
    expected, _ = first_piola_and_tangent(material, deformation_gradients)
    np.testing.assert_allclose(first_piola(material, deformation_gradients), expected, rtol=0,
                               atol=1e-13 * np.abs(expected).max())


@pytest.mark.parametrize("material", MATERIALS)
def test_pk2_stress_is_the_energy_derivative_in_strain(material, deformation_gradients):
    """S_IJ = dW / dE_IJ, with W evaluated at the stretch U(E) (W depends on F only through C)."""
    strain = green_lagrange_strain(deformation_gradients)
    stress, _ = material.pk2_stress(deformation_gradients)
    finite_difference = np.zeros_like(stress)
    for i in range(2):
        for j in range(2):
            step = STEP * symmetric_unit(i, j)
            finite_difference[:, i, j] = (material.energy(stretch_from_strain(strain + step))
                                          - material.energy(stretch_from_strain(strain - step))) / (2 * STEP)
    np.testing.assert_allclose(stress, finite_difference, rtol=0, atol=FD_RTOL * np.abs(stress).max())


@pytest.mark.parametrize("material", MATERIALS)
def test_material_tangent_is_the_pk2_derivative(material, deformation_gradients):
    """C_IJKL = dS_IJ / dE_KL."""
    strain = green_lagrange_strain(deformation_gradients)
    _, tangent = material.pk2_stress(deformation_gradients)
    finite_difference = np.zeros_like(tangent)
    for k in range(2):
        for l in range(2):
            step = STEP * symmetric_unit(k, l)
            plus, _ = material.pk2_stress(stretch_from_strain(strain + step))
            minus, _ = material.pk2_stress(stretch_from_strain(strain - step))
            finite_difference[:, :, :, k, l] = (plus - minus) / (2 * STEP)
    np.testing.assert_allclose(tangent, finite_difference, rtol=0, atol=FD_RTOL * np.abs(tangent).max())


@pytest.mark.parametrize("material", MATERIALS)
def test_first_piola_tangent_is_the_first_piola_derivative(material, deformation_gradients):
    """A_iJkL = dP_iJ / dF_kL (eq. 3.13-3.16), geometric term included."""
    _, tangent = first_piola_and_tangent(material, deformation_gradients)
    finite_difference = np.zeros_like(tangent)
    for k in range(2):
        for l in range(2):
            step = STEP * unit(k, l)
            plus, _ = first_piola_and_tangent(material, deformation_gradients + step)
            minus, _ = first_piola_and_tangent(material, deformation_gradients - step)
            finite_difference[:, :, :, k, l] = (plus - minus) / (2 * STEP)
    np.testing.assert_allclose(tangent, finite_difference, rtol=0, atol=FD_RTOL * np.abs(tangent).max())


@pytest.mark.parametrize("material", MATERIALS)
def test_tangents_have_hyperelastic_symmetries(material, deformation_gradients):
    """A_iJkL = A_kLiJ (a second derivative of W), and C has major and minor symmetry."""
    _, tangent = material.pk2_stress(deformation_gradients)
    _, first_tangent = first_piola_and_tangent(material, deformation_gradients)
    scale = np.abs(first_tangent).max()
    np.testing.assert_allclose(first_tangent, first_tangent.transpose(0, 3, 4, 1, 2), atol=1e-13 * scale)
    np.testing.assert_allclose(tangent, tangent.transpose(0, 3, 4, 1, 2), atol=1e-13 * scale)
    np.testing.assert_allclose(tangent, tangent.transpose(0, 2, 1, 3, 4), atol=1e-13 * scale)


@pytest.mark.parametrize("material", MATERIALS)
def test_reference_state_is_stress_free_and_linear_elastic(material):
    """At F = I: no stress and the plane-strain Hooke tangent lambda d_ij d_kl + mu (d_ik d_jl + d_il d_jk)."""
    identity = np.eye(2)[None]
    stress, tangent = material.pk2_stress(identity)
    i = np.eye(2)
    hooke = material.lame_lambda * np.einsum("ij,kl->ijkl", i, i) + material.lame_mu * (
        np.einsum("ik,jl->ijkl", i, i) + np.einsum("il,jk->ijkl", i, i))
    np.testing.assert_allclose(stress, 0.0, atol=1e-15)
    np.testing.assert_allclose(tangent[0], hooke, rtol=1e-14, atol=1e-15)
    assert material.energy(identity)[0] == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("material", MATERIALS)
def test_energy_and_pk2_are_frame_indifferent(material, deformation_gradients):
    """W(R F) = W(F) and S(R F) = S(F) for a rotation R."""
    angle = 1.1
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    rotated = rotation @ deformation_gradients
    np.testing.assert_allclose(material.energy(rotated), material.energy(deformation_gradients),
                               rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(material.pk2_stress(rotated)[0], material.pk2_stress(deformation_gradients)[0],
                               rtol=1e-11, atol=1e-14)
