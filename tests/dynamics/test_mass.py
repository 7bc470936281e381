"""Mass model: de Leva tables, mesh volumes, object mass and inertia against closed forms."""
import numpy as np
import pytest
import trimesh

from intercap.dynamics import mass


@pytest.mark.parametrize("female", [0.0, 1.0, 0.3])
def test_segment_table_masses_sum_to_one(female):
    table = mass.de_leva_table(female)
    rows = mass.ANNY_SEGMENTS
    total = sum(table[row][0] for _, row, *_ in rows)
    assert total == pytest.approx(1.0, abs=2e-3)  # both sides' limbs, the trunk and the head


def test_box_volume_and_inertia():
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    assert mass.mesh_volume(box.vertices, box.faces) == pytest.approx(0.006)
    com, inertia = mass.object_inertia(box.vertices, box.faces, 3.0)
    assert np.allclose(com, 0, atol=1e-12)
    expected = 3.0 / 12 * np.diag([0.2**2 + 0.1**2, 0.3**2 + 0.1**2, 0.3**2 + 0.2**2])
    assert np.allclose(inertia, expected, atol=1e-9)


def test_open_mesh_has_no_volume():
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    with pytest.raises(mass.MassError, match="not watertight"):
        mass.mesh_volume(box.vertices, box.faces[:-2])


def test_object_mass_sources():
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    assert mass.object_mass(1.5, 700, box.vertices, box.faces) == (1.5, "session.yaml object.mass_kg")
    m, how = mass.object_mass(None, 700, box.vertices, box.faces)
    assert m == pytest.approx(0.7) and "density" in how
    m, how = mass.object_mass(None, None, box.vertices, box.faces)
    assert np.isnan(m) and "neither object.mass_kg nor object.density_kg_m3" in how


def test_segment_inertia_principal_moments():
    I = mass.segment_inertia(2.0, 0.4, np.array([0.3, 0.25, 0.1]), np.array([0, 0, -1.0]), np.array([1.0, 0, 0]))
    # longitudinal axis z, transverse x, sagittal y
    assert np.allclose(np.diag(I), [2 * (0.25 * 0.4) ** 2, 2 * (0.3 * 0.4) ** 2, 2 * (0.1 * 0.4) ** 2])
    assert np.allclose(I, I.T)
