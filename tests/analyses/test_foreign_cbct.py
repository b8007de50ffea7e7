"""A CBCT series another tool wrote plans as the project's own phantom does (issue 25's
Done-when): the phantom's volume, resampled onto another grid and written here with pydicom
directly (not systems.anatomy.dicom_ct): files named by their SOP instance UIDs and written in
shuffled order, rows running towards -y (so the slices run towards -z), anisotropic voxels,
Implicit VR Little Endian, signed stored values with slope 0.5 and intercept -1000, a nominal
SliceThickness that is not the spacing, no SpacingBetweenSlices, its own UIDs.

By default a coarse phantom (1.5 mm) resampled to 1.2 mm pixels / 1.3 mm slices reads back to
the same HU at the same patient positions and fits the FPSM as the phantom-as-written does;
under ``sweep`` the 0.4 mm phantom resampled to 0.3 mm pixels / 0.35 mm slices is planned
(small sizes) beside the phantom-as-written and the two plans agree within the issue's bounds.
"""

from __future__ import annotations

import json

import numpy as np
import pydicom
import pytest
import yaml
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ImplicitVRLittleEndian, generate_uid
from scipy import ndimage

from implantplan.analyses import pipeline
from implantplan.analyses.case import default_case_path, load_case
from implantplan.analyses.phantom import make_phantom_folder
from implantplan.systems.anatomy.cbct import Volume, read_dicom_series
from tests.analyses.cases import SMALL
from tests.analyses.test_phantom import curve_distance

IOP = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0)  # columns along +x, rows along -y: slices along -z
SLOPE, INTERCEPT = 0.5, -1000.0


def resample(volume: Volume, spacing_mm, *, iop=IOP) -> Volume:
    """``volume`` trilinearly resampled onto a grid of ``spacing_mm`` (along columns, rows,
    slices) with orientation ``iop`` covering the same patient-frame box (voxel centres inside
    the original's)."""
    u, w = np.array(iop[:3]), np.array(iop[3:])
    n = np.cross(u, w)
    R = np.column_stack([u, w, n])
    corners = volume.to_patient(np.array(
        [[i, j, k] for i in (0, volume.hu.shape[2] - 1) for j in (0, volume.hu.shape[1] - 1)
         for k in (0, volume.hu.shape[0] - 1)], dtype=float))
    local = corners @ R  # the box in the new axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    sp = np.asarray(spacing_mm, dtype=float)
    ni, nj, nk = (np.floor((hi - lo) / sp + 1e-9).astype(int) + 1).tolist()
    affine = np.eye(4)
    affine[:3, :3] = R * sp
    affine[:3, 3] = R @ lo
    out = Volume(np.empty((nk, nj, ni), dtype=np.float32), affine)
    inv = np.linalg.inv(volume.affine)
    jj, ii = np.meshgrid(np.arange(nj), np.arange(ni), indexing="ij")
    for k in range(nk):
        ijk = np.column_stack([ii.ravel(), jj.ravel(), np.full(ii.size, k)]).astype(float)
        old = out.to_patient(ijk) @ inv[:3, :3].T + inv[:3, 3]  # (i, j, k) in the original
        out.hu[k] = ndimage.map_coordinates(volume.hu, old[:, ::-1].T, order=1,
                                            mode="nearest").reshape(nj, ni)
    return out


def write_foreign_series(folder, volume: Volume, *, seed: int = 7) -> dict:
    """``volume`` as a CT series written with pydicom directly (see the module docstring);
    returns its identifiers."""
    folder.mkdir(parents=True, exist_ok=True)
    u, w = volume.affine[:3, 0], volume.affine[:3, 1]
    d_col, d_row = np.linalg.norm(u), np.linalg.norm(w)
    iop = np.concatenate([u / d_col, w / d_row])
    stored = np.rint((volume.hu - INTERCEPT) / SLOPE)
    assert stored.min() >= -32768 and stored.max() <= 32767
    stored = stored.astype(np.int16)
    ids = {"study": generate_uid(), "series": generate_uid(), "frame": generate_uid()}
    nk = stored.shape[0]
    for k in np.random.default_rng(seed).permutation(nk):
        sop = generate_uid()
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
        meta.MediaStorageSOPInstanceUID = sop
        meta.TransferSyntaxUID = ImplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, sop
        ds.Modality, ds.Manufacturer = "CT", "Another Vendor"
        ds.PatientID, ds.PatientName = "FOREIGN-1", "Foreign^Tool"
        ds.StudyInstanceUID, ds.SeriesInstanceUID = ids["study"], ids["series"]
        ds.FrameOfReferenceUID = ids["frame"]
        ds.SeriesNumber, ds.InstanceNumber = 3, int(nk - k)  # numbered against position
        ds.ImageOrientationPatient = [f"{x:.6f}" for x in iop]
        pos = volume.to_patient(np.array([[0.0, 0.0, float(k)]]))[0]
        ds.ImagePositionPatient = [f"{x:.5f}" for x in pos]
        ds.PixelSpacing = [f"{d_row:.6g}", f"{d_col:.6g}"]
        ds.SliceThickness = "0.5"  # nominal reconstruction thickness, not the spacing
        ds.Rows, ds.Columns = stored.shape[1], stored.shape[2]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = f"{SLOPE:g}", f"{INTERCEPT:g}"
        ds.PixelData = stored[k].tobytes()
        ds.save_as(folder / sop, enforce_file_format=True)
    return ids


def _sampled_at(volume: Volume, p_mm: np.ndarray) -> np.ndarray:
    """``volume``'s HU at patient positions (mm), trilinear."""
    inv = np.linalg.inv(volume.affine)
    ijk = p_mm @ inv[:3, :3].T + inv[:3, 3]
    return ndimage.map_coordinates(volume.hu, ijk[:, ::-1].T, order=1, mode="nearest")


def _foreign_case(phantom_dir, foreign_ct, out_dir, *, small: bool):
    """The phantom's case file with ``mesh.path`` the foreign series (and, ``small``, the small
    sizes), written into ``out_dir``; and the phantom's own case file at the same sizes."""
    data = yaml.safe_load((phantom_dir / "case.yaml").read_text())
    data["anatomy"]["canals_file"] = str(phantom_dir / "canals.yaml")
    if small:
        for section, values in SMALL.items():
            data[section].update(values)
        data["safety"]["registration_samples"] = 20
    own = dict(data, mesh={**data["mesh"], "path": str(phantom_dir / "ct")})
    other = dict(data, mesh={**data["mesh"], "path": str(foreign_ct)}, name="default-foreign")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "own.yaml").write_text(yaml.safe_dump(own))
    (out_dir / "foreign.yaml").write_text(yaml.safe_dump(other))
    return out_dir / "own.yaml", out_dir / "foreign.yaml"


COARSE_MM, COARSE_SPACING = 1.5, (1.2, 1.2, 1.3)


@pytest.fixture(scope="module")
def coarse(tmp_path_factory):
    """The coarse phantom as the project writes it, and the same volume resampled and written by
    the foreign writer: (phantom folder, its volume, the foreign folder, the volume written)."""
    root = tmp_path_factory.mktemp("foreign")
    make_phantom_folder(default_case_path(), root / "phantom", voxel_mm=COARSE_MM, noise_hu=20.0,
                        seed=None, force=False)
    own = read_dicom_series(root / "phantom" / "ct")
    other = resample(own, COARSE_SPACING)
    write_foreign_series(root / "foreign", other)
    return root / "phantom", own, root / "foreign", other


def test_the_foreign_series_reads_back_in_the_patient_frame(coarse):
    _, own, folder, written = coarse
    files = sorted(p.name for p in folder.iterdir())
    assert len(files) == written.hu.shape[0] and not any(f.startswith("CT") for f in files)
    first = pydicom.dcmread(folder / files[0], stop_before_pixels=True)
    assert first.file_meta.TransferSyntaxUID == ImplicitVRLittleEndian
    assert float(first.RescaleSlope) == SLOPE and "SpacingBetweenSlices" not in first
    back = read_dicom_series(folder)
    np.testing.assert_allclose(back.spacing, COARSE_SPACING, atol=1e-5)
    # columns along +x, rows along -y, slices along -z: the reader's affine is the writer's
    np.testing.assert_allclose(back.affine, written.affine, atol=1e-4)
    np.testing.assert_allclose(back.affine[:3, :3] / back.spacing,
                               np.diag([1.0, -1.0, -1.0]), atol=1e-9)
    np.testing.assert_array_less(np.abs(back.hu - written.hu), SLOPE / 2 + 1e-3)  # HU, rounding
    assert back.info["patient_id"] == "FOREIGN-1"
    # the same patient-frame content as the phantom: HU at the phantom's voxel centres (inside
    # the foreign grid), where the phantom is locally flat (no edge within a voxel), agree
    k, j, i = np.meshgrid(*(np.arange(2, n - 2, 3) for n in own.hu.shape), indexing="ij")
    ijk = np.column_stack([i.ravel(), j.ravel(), k.ravel()]).astype(float)
    flat = (ndimage.maximum_filter(own.hu, 3) - ndimage.minimum_filter(own.hu, 3))[
        k.ravel(), j.ravel(), i.ravel()] < 200
    p = own.to_patient(ijk[flat])
    np.testing.assert_allclose(_sampled_at(back, p), own.hu[k.ravel(), j.ravel(), i.ravel()][
        flat], atol=100)  # measured 57 HU (the noise, interpolated twice)
    assert flat.sum() > 1000


def test_the_foreign_series_fits_as_the_phantom_does(coarse):
    phantom_dir, _, folder, _ = coarse
    own_file, foreign_file = _foreign_case(phantom_dir, folder, phantom_dir.parent / "cases",
                                           small=False)
    fits = [pipeline.fit_stage(load_case(f)) for f in (own_file, foreign_file)]
    assert fits[1].cbct.info["patient_id"] == "FOREIGN-1"
    d = curve_distance(fits[0].fpsm, fits[1].fpsm)
    assert d.max() < COARSE_MM * 1e-3, d  # within one of the phantom's voxels (0.96 mm)
    case = load_case(foreign_file)
    sites = pipeline.site_stage(case, fits[1])
    assert np.all(sites.distance < 0.5 * COARSE_MM * 1e-3) and np.all(sites.axis_into_cavity)


@pytest.mark.sweep
def test_a_foreign_04mm_series_plans_like_the_phantom(tmp_path):
    """The 0.4 mm phantom resampled to 0.3 mm pixels / 0.35 mm slices, planned at the case's
    sizes beside the phantom as written (measured: curves within 0.37 mm, targets within
    0.002 mm / 0.05 deg; at the small sizes the small FPSM and PSO alone move them 0.62 mm /
    1.0 deg while the two air surfaces agree to 0.05 mm on average)."""
    from implantplan.analyses.cli import main
    from implantplan.systems.fpsm.model import Fpsm

    make_phantom_folder(default_case_path(), tmp_path / "phantom", voxel_mm=0.4, noise_hu=20.0,
                        seed=None, force=False)
    other = resample(read_dicom_series(tmp_path / "phantom" / "ct"), (0.3, 0.3, 0.35))
    write_foreign_series(tmp_path / "series", other)
    cases = _foreign_case(tmp_path / "phantom", tmp_path / "series", tmp_path / "cases",
                          small=False)
    plans = []
    for case_file, name in zip(cases, ("own", "foreign"), strict=True):
        code = main(["plan", str(case_file), "--out", str(tmp_path / f"plan_{name}"), "--runs",
                     "0", "--no-figures", "--quiet"])
        assert code == 0, name
        plans.append(json.loads((tmp_path / f"plan_{name}" / "plan.json").read_text()))
    own, foreign = plans
    assert foreign["scan"]["patient_id"] == "FOREIGN-1"
    assert foreign["scan"]["spacing_mm"] == pytest.approx([0.3, 0.3, 0.35], abs=1e-5)
    assert foreign["passed"] and all(c["pass"] for c in foreign["checks"])
    assert [c["id"] for c in foreign["checks"]] == [c["id"] for c in own["checks"]]
    d = curve_distance(Fpsm.load(tmp_path / "plan_own" / "fpsm.json"),
                       Fpsm.load(tmp_path / "plan_foreign" / "fpsm.json"))
    assert d.max() < 0.5e-3, d
    for so, sf in zip(own["sites"], foreign["sites"], strict=True):
        assert so["placement"]["valid"] and sf["placement"]["valid"]
        Xo, Xf = (np.array(s["feeding_target"]["X_CT"]) for s in (so, sf))
        assert np.linalg.norm(Xo[:3, 3] - Xf[:3, 3]) < 1e-3
        cos = np.clip((np.trace(Xo[:3, :3].T @ Xf[:3, :3]) - 1) / 2, -1, 1)
        assert np.degrees(np.arccos(cos)) < 1.0
