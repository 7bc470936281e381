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


@pytest.mark.parametrize("table", [mass.DE_LEVA_MALE, mass.DE_LEVA_FEMALE])
def test_de_leva_published_masses_sum_to_100_percent(table):
    total = sum(row[0] * (1 if name in mass.UNPAIRED else 2) for name, row in table.items())
    assert total == pytest.approx(100.0, abs=0.011)  # the female column sums to 99.99 % as published
    renormalised = mass.de_leva_table(1.0 if table is mass.DE_LEVA_FEMALE else 0.0)
    assert sum(r[0] * (1 if k in mass.UNPAIRED else 2) for k, r in renormalised.items()) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("sex, segment, expected", [
    # de Leva (1996) Table 4: mass %, CM %, radii of gyration % (sagittal, transverse, longitudinal)
    ("male", "thigh", (14.16, 40.95, 32.9, 32.9, 14.9)),
    ("female", "thigh", (14.78, 36.12, 36.9, 36.4, 16.2)),
    ("male", "hand", (0.61, 79.00, 62.8, 51.3, 40.1)),
    ("female", "lower_trunk", (12.47, 49.20, 43.3, 40.2, 44.4)),
    ("male", "head", (6.94, 50.02, 30.3, 31.5, 26.1)),  # vertex -> cervicale
    ("female", "upper_trunk", (15.45, 50.50, 46.6, 31.4, 44.9)),  # cervicale -> xiphoid
    ("male", "shank", (4.33, 43.95, 25.1, 24.6, 10.2)),  # knee -> ankle joint centre
    ("female", "shank", (4.81, 43.52, 26.7, 26.3, 9.2)),
    ("female", "foot", (1.29, 40.14, 29.9, 27.9, 13.9)),
])
def test_de_leva_spot_values(sex, segment, expected):
    table = mass.DE_LEVA_MALE if sex == "male" else mass.DE_LEVA_FEMALE
    assert table[segment] == pytest.approx(expected, abs=1e-9)
