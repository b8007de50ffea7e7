"""The default surgical case: the jaw-opening model (open_mouth) and the bundled case's sites.

The opening is checked on a box split by the occlusal plane z = 0 (hand-derived rotations), the
default case on the real ArtiSynth oral mesh: opened, fitted, and both implant sites must get a
collision-free placement of the paper's contra-angle tool (rod radius 6 mm, d12 = 31 mm) that the
exhaustive grid confirms.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml
from implantplan.systems.fpsm.oral_mesh import center_frame, face_flips, load_oral_mesh, open_mouth

ROOT = Path(__file__).resolve().parents[3]
CASE = ROOT / "models" / "cases" / "default.yaml"
MM = 1e-3

# hinge 0.1 m in front (+x) and 0.03 m above the occlusal plane z = 0; axis -y, so a positive
# angle turns the -x side (the "chin") down
HINGE = dict(
    hinge_point=[0.1, 0.0, 0.03],
    hinge_axis=[0.0, -1.0, 0.0],
    occlusal_point=[0.0, 0.0, 0.0],
    occlusal_normal=[0.0, 0.0, 1.0],
)


def _box() -> trimesh.Trimesh:
    """A 0.1 m box around the origin, subdivided so vertices sit in and around the blend band."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.01)
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def test_vertex_far_below_the_plane_rotates_rigidly_about_the_hinge():
    box = _box()
    out = open_mouth(box, 30.0, **HINGE, blend=0.02)
    V0, V1 = np.asarray(box.vertices), np.asarray(out.vertices)
    k = int(np.argmin(np.linalg.norm(V0 - [-0.05, -0.05, -0.05], axis=1)))  # the box corner
    # relative to the hinge: (-0.15, ., -0.08); rotating by 30 deg about -y is, in the xz plane,
    # x' = x cos a - z sin a, z' = x sin a + z cos a
    c, s = np.sqrt(3) / 2, 0.5
    x, z = -0.15, -0.08
    expected = [0.1 + x * c - z * s, -0.05, 0.03 + x * s + z * c]  # = (-0.0899, -0.05, -0.1136)
    np.testing.assert_allclose(V1[k], expected, atol=1e-12)
    assert V1[k, 2] < V0[k, 2]  # the chin goes down
    # every vertex of the lower jaw (below the band) keeps its distance to the hinge
    below = V0[:, 2] <= -0.01
    d0 = np.linalg.norm(V0[below] - HINGE["hinge_point"], axis=1)
    d1 = np.linalg.norm(V1[below] - HINGE["hinge_point"], axis=1)
    np.testing.assert_allclose(d1, d0, atol=1e-12)


def test_vertices_above_the_band_do_not_move_and_no_face_turns_over():
    box = _box()
    out = open_mouth(box, 25.0, **HINGE, blend=0.02)
    V0, V1 = np.asarray(box.vertices), np.asarray(out.vertices)
    above = V0[:, 2] >= 0.01
    assert above.sum() > 50
    np.testing.assert_array_equal(V1[above], V0[above])
    # inside the band the vertices move, but by less than the rigid rotation
    band = np.abs(V0[:, 2]) < 0.01 - 1e-9
    moved = np.linalg.norm(V1 - V0, axis=1)
    assert np.all(moved[band & (V0[:, 2] < 0.0)] > 0)
    info = out.metadata["implantplan"]["open_mouth"]
    assert info["inverted_faces"] == 0 and info["degenerate_faces"] == 0
    np.testing.assert_array_equal(out.faces, box.faces)
    # connectivity is kept: the opened box is still closed
    assert out.is_watertight


def test_angle_zero_is_the_identity():
    box = _box()
    out = open_mouth(box, 0.0, **HINGE)
    np.testing.assert_array_equal(out.vertices, box.vertices)


def test_face_flips_counts_a_mirrored_mesh_as_all_inverted():
    box = _box()
    mirrored = trimesh.Trimesh(box.vertices * [1, 1, -1], box.faces, process=False)
    inverted, degenerate = face_flips(box, mirrored, [0, 1, 0], np.zeros(len(box.vertices)))
    # a mirror M maps a face normal n to det(M) M n = -M n: the side faces (n_z = 0) turn
    # over, the top and bottom (n = +-z, M n = -n) keep their direction
    n = box.face_normals
    assert inverted == int(np.count_nonzero(np.abs(n[:, 2]) < 0.5)) == 2048
    assert degenerate == 0
    flat = trimesh.Trimesh(box.vertices * [1, 1, 0], box.faces, process=False)
    _, degenerate = face_flips(box, flat, [0, 1, 0], np.zeros(len(box.vertices)))
    assert degenerate == int(np.count_nonzero(np.abs(n[:, 2]) < 0.5))


@settings(max_examples=25, deadline=None)
@given(angle=st.floats(0.0, 45.0), blend=st.floats(0.002, 0.05))
def test_rigid_below_fixed_above_for_any_angle_and_blend(angle, blend):
    box = _box()
    out = open_mouth(box, angle, **HINGE, blend=blend)
    V0, V1 = np.asarray(box.vertices), np.asarray(out.vertices)
    above = V0[:, 2] >= blend / 2
    np.testing.assert_array_equal(V1[above], V0[above])
    below = V0[:, 2] <= -blend / 2
    a = np.deg2rad(angle)
    rel = V0[below] - HINGE["hinge_point"]
    x = rel[:, 0] * np.cos(a) - rel[:, 2] * np.sin(a)
    z = rel[:, 0] * np.sin(a) + rel[:, 2] * np.cos(a)
    np.testing.assert_allclose(V1[below][:, 0], 0.1 + x, atol=1e-12)
    np.testing.assert_allclose(V1[below][:, 2], 0.03 + z, atol=1e-12)
    np.testing.assert_allclose(V1[:, 1], V0[:, 1], atol=1e-15)  # the hinge axis is y


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"angle_deg": -1.0}, "mouth_opening_deg"),
        ({"angle_deg": 50.0}, "mouth_opening_deg"),
        ({"angle_deg": float("nan")}, "mouth_opening_deg"),
        ({"angle_deg": "wide"}, "mouth_opening_deg"),
        ({"hinge_axis": [0.0, 0.0, 0.0]}, "hinge_axis"),
        ({"hinge_point": [0.1, 0.0]}, "hinge_point"),
        ({"hinge_point": [0.1, np.inf, 0.0]}, "hinge_point"),
        ({"occlusal_normal": [0, 0, 0]}, "occlusal_normal"),
        ({"occlusal_point": "here"}, "occlusal_point"),
        ({"blend": 0.0}, "blend"),
        ({"blend": -0.01}, "blend"),
    ],
)
def test_bad_parameters_are_input_errors(kwargs, field):
    args = {"angle_deg": 20.0, **HINGE, "blend": 0.02, **kwargs}
    angle = args.pop("angle_deg")
    with pytest.raises(InputError) as err:
        open_mouth(_box(), angle, **args)
    assert err.value.field == field


# -- the bundled default case ------------------------------------------------------------------


def _opened_default(case):
    m = case["mesh"]
    assert m["path"] == "package://implantplan/oral/oralCavityMesh.obj"
    mesh = load_oral_mesh(ROOT / "models" / "oral" / "oralCavityMesh.obj", units=m["units"])
    opened = open_mouth(
        mesh,
        m["mouth_opening_deg"],
        hinge_point=np.asarray(m["hinge_point_mm"]) * MM,
        hinge_axis=m["hinge_axis"],
        occlusal_point=np.asarray(m["occlusal_point_mm"]) * MM,
        occlusal_normal=m["occlusal_normal"],
        blend=m["opening_blend_mm"] * MM,
    )
    return mesh, opened


def test_default_case_opens_the_real_mesh_cleanly():
    case = read_yaml(CASE)
    mesh, opened = _opened_default(case)
    info = opened.metadata["implantplan"]["open_mouth"]
    assert info["inverted_faces"] == 0 and info["degenerate_faces"] == 0
    V0, V1 = np.asarray(mesh.vertices), np.asarray(opened.vertices)
    # the floor of the scan (z = 54.1 mm, far below the band) turns down and back about the hinge
    floor = V0[:, 2] < 60 * MM
    hinge = np.asarray(case["mesh"]["hinge_point_mm"]) * MM
    assert floor.sum() > 100
    r0, r1 = V0[floor] - hinge, V1[floor] - hinge
    axis = np.asarray(case["mesh"]["hinge_axis"], float)
    # the rotation angle is measured in the plane normal to the hinge axis
    r0p, r1p = r0 - np.outer(r0 @ axis, axis), r1 - np.outer(r1 @ axis, axis)
    signed = np.arctan2(np.cross(r0p, r1p) @ axis, np.einsum("ij,ij->i", r0p, r1p))
    np.testing.assert_allclose(np.rad2deg(signed), case["mesh"]["mouth_opening_deg"], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(r1, axis=1), np.linalg.norm(r0, axis=1))
    # well in front of the hinge the floor goes down (right below it, it swings backwards)
    ahead = V0[floor, 0] < hinge[0] - 30 * MM
    assert ahead.sum() > 100 and np.all(V1[floor][ahead, 2] < V0[floor][ahead, 2])
    # the lower jaw at the front teeth (96 mm from the hinge) opens by 2 L sin(a / 2) ~ 42 mm
    front = np.array([56.3, 0.0, 97.8]) * MM
    L = np.linalg.norm((front - hinge)[[0, 2]])
    assert 35e-3 < 2 * L * np.sin(np.deg2rad(case["mesh"]["mouth_opening_deg"]) / 2) < 50e-3


PAPER_ROD_MM, PAPER_D12_MM = 6.0, 31.0  # seed 000 Sec. 5.2's tool (the actuator's rod and d12 too)


@pytest.fixture(scope="module")
def default_plan():
    """The default case opened, fitted (exact, 15 x 15 x 150) and both sites placed."""
    from implantplan.systems.fpsm.fit import fit_fpsm
    from implantplan.systems.placement.planner import place_instrument

    case = read_yaml(CASE)
    assert case["schema_version"] == 1 and case["placement"]["objective"] == "eq14"
    _, opened = _opened_default(case)
    c = case["center"]
    X_WC = center_frame(np.asarray(c["origin_mm"]) * MM, c["z_axis"], x_hint=c["x_hint"])
    fp = case["fpsm"]
    assert (fp["slices"], fp["control_points"], fp["samples"], fp["method"]) == (
        15,
        15,
        150,
        "exact",
    )
    fpsm = fit_fpsm(
        opened,
        X_WC,
        slices=fp["slices"],
        control_points=fp["control_points"],
        samples=fp["samples"],
        method=fp["method"],
        margin=fp["margin_mm"] * MM,
        z_range=np.asarray(fp["z_range_mm"]) * MM,
        close_open_cuts=case["mesh"]["close_open_cuts"],
        check_factor=0,
    )
    placements = [
        place_instrument(
            fpsm,
            np.asarray(site["position_mm"]) * MM,
            site["axis"],
            rod_radius=PAPER_ROD_MM * MM,
            implant_length=PAPER_D12_MM * MM,
            objective=case["placement"]["objective"],
            seed=case["seed"],
        )
        for site in case["sites"]
    ]
    return case, opened, X_WC, fpsm, placements


def test_default_case_sites_have_a_safe_placement_for_the_papers_tool(default_plan):
    case, _, _, fpsm, placements = default_plan
    names = [s["name"] for s in case["sites"]]
    assert names == ["36", "46"]
    for site, placement in zip(case["sites"], placements, strict=True):
        p = np.asarray(site["position_mm"]) * MM
        assert p[1] < -0.015 and abs(p[0]) > 0.01  # lower jaw, side of the arch
        assert (p[0] > 0) == (site["name"] == "36")  # Center +X is the patient's left
        # on the scanned tissue (the case's site_check), just outside the conservative FPSM wall
        assert -2e-3 < float(fpsm.d_safe(p)) <= 0
        assert "rod_radius_mm" not in site  # the case's actuator carries its own shapes
        assert placement.valid, placement.reason
        assert placement.f_safe_line1 > 3e-3 and placement.f_safe_line2 > 3e-3
        # the tool stays above the implant (d_T >= d12) and the grid finds no better placement
        assert placement.d_T >= PAPER_D12_MM * MM
        assert placement.grid["F_pso_minus_grid"] < 1e-6
        assert placement.grid["distance_d_T"] < 1e-3


def test_case_figures_write_pngs(default_plan, tmp_path):
    from implantplan.analyses.case_figures import plot_mouth_opening, plot_placements

    case, opened, X_WC, fpsm, placements = default_plan
    box = _box()
    a = plot_mouth_opening(
        box,
        open_mouth(box, 20.0, **HINGE),
        tmp_path / "o.png",
        planes_y=(0.0, 0.02),
        hinge_point=HINGE["hinge_point"],
        occlusal_point=HINGE["occlusal_point"],
        occlusal_normal=HINGE["occlusal_normal"],
    )
    b = plot_placements(opened, X_WC, fpsm, placements, ["36", "46"], tmp_path / "p.png")
    for path in (a, b):
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_site_scan_finds_the_default_sites_valid(default_plan):
    from implantplan.analyses.case_figures import scan_sites

    case, opened, X_WC, fpsm, placements = default_plan
    ranked = scan_sites(
        fpsm,
        mesh=opened,
        X_WC=X_WC,
        rod_radius=6e-3,
        implant_length=31e-3,
        slices=[8],
        angles_deg=(-120, -60, -90),
        lingual_tilts_deg=(15.0,),
        mesial_tilts_deg=(0.0,),
    )
    assert len(ranked) == 3
    assert [c["F"] for c in ranked] == sorted(c["F"] for c in ranked)
    for site, placement in zip(case["sites"], placements, strict=True):
        c = min(
            ranked, key=lambda c: np.linalg.norm(c["site"] - np.asarray(site["position_mm"]) * MM)
        )
        assert np.linalg.norm(c["site"] - np.asarray(site["position_mm"]) * MM) < 0.1 * MM
        np.testing.assert_allclose(c["axis"], site["axis"], atol=1e-6)
        assert c["valid"]
        # a coarse grid cannot beat the PSO + fine grid optimum, and is close to it
        assert placement.F_safe - 1e-9 <= c["F"] < placement.F_safe + 0.005


def test_the_paper_tool_here_has_the_actuators_rod_and_d12():
    from implantplan.analyses.case import default_case_path, load_case

    case = load_case(default_case_path())
    inst = case.instrument_at(case.sites[0])
    assert (inst.rod_radius, inst.implant_length) == pytest.approx(
        (PAPER_ROD_MM * MM, PAPER_D12_MM * MM))
