"""CBCT in (systems.anatomy.cbct) and the phantom (systems.anatomy.phantom, dicom_ct): a coarse
phantom of the bundled scan read back lands on the scan; a series written here with pydicom
directly (shuffled files, anisotropic spacing, other orientation and pixel encoding) reads back
to the analytic surface; every bad series is an InputError naming the file."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
import trimesh
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from implantplan.systems.anatomy.cbct import air_surface, load_cbct_scan, read_dicom_series
from implantplan.systems.anatomy.dicom_ct import SeriesIds, write_ct_series
from implantplan.systems.anatomy.phantom import (
    PhantomSpec,
    column_air_fraction,
    distance_to_polyline,
    make_phantom,
)
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.oral_mesh import DEFAULT_CAVITY, close_open_cuts, load_oral_mesh

VOXEL = 1.5e-3


@pytest.fixture(scope="module")
def scan():
    return load_oral_mesh(DEFAULT_CAVITY["path"])


@pytest.fixture(scope="module")
def phantom(scan):
    entries = np.array([[0.0795, -0.0143, 0.0913], [0.0794, 0.0143, 0.0912]])
    apexes = entries - [0.0042, 0.0026, 0.0084]
    return make_phantom(scan, PhantomSpec(voxel=VOXEL), seed=0, implants=(entries, apexes))


@pytest.fixture(scope="module")
def series(phantom, tmp_path_factory):
    folder = tmp_path_factory.mktemp("ct")
    write_ct_series(folder, phantom.hu, phantom.origin * 1e3, [VOXEL * 1e3] * 3,
                    ids=SeriesIds(patient_id="P1"))
    return folder


def test_column_air_fraction_of_a_box_is_the_exact_overlap():
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])  # z from -0.5 to 0.5
    edges = np.array([-1.0, -0.6, -0.4, 0.0, 0.45, 0.55, 1.0])
    frac, first, last = column_air_fraction(box, np.array([0.1, 2.0]), np.array([0.2]), edges)
    np.testing.assert_allclose(frac[0, 0], [0, 0.5, 1, 1, 0.5, 0], atol=1e-12)
    np.testing.assert_array_equal(frac[0, 1], 0)  # a column outside the box
    assert first[0, 0] == pytest.approx(-0.5) and last[0, 0] == pytest.approx(0.5)
    assert np.isnan(first[0, 1])


def test_phantom_has_the_tissue_classes_and_canals(phantom):
    hu = phantom.hu
    assert hu.dtype == np.int16 and hu.size < 5e6
    # air, soft tissue, cortical bone, enamel
    for lo, hi in ((-1100, -900), (0, 100), (1300, 1700), (2300, 2700)):
        assert np.count_nonzero((hu > lo) & (hu < hi)) > 1000
    assert len(phantom.canals) == 2
    for c in phantom.canals:
        assert np.all(np.diff(c[:, 0]) > 0) and np.ptp(c[:, 1]) == 0 and np.ptp(c[:, 2]) == 0


def test_phantom_read_back_lands_on_the_scan(series, scan, phantom):
    cbct = load_cbct_scan(series, air_threshold_hu=-500, bone_threshold_hu=300)
    assert cbct.info["patient_id"] == "P1" and cbct.info["files"] == phantom.hu.shape[0]
    np.testing.assert_allclose(cbct.volume.affine[:3, 3], phantom.origin * 1e3, atol=1e-6)
    assert cbct.mesh.volume < 0  # seen from the inside, as the bundled scan
    closed = close_open_cuts(scan)[0]
    _, d, _ = trimesh.proximity.ProximityQuery(closed).on_surface(cbct.mesh.vertices[::10])
    assert np.max(d) < VOXEL  # within a voxel of the scan (0.4 mm voxels: 0.3 mm, measured)
    assert np.mean(d) < 0.2 * VOXEL
    assert cbct.bone is not None and cbct.bone.area > 0
    assert abs(cbct.mesh.volume - closed.volume) < 0.03 * abs(closed.volume)


def _slice(k, pixels, *, spacing, origin, iop, series_uid, study_uid, frame_uid):
    """One CT slice written with pydicom directly: signed pixels, slope 2 intercept -1000."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.PatientID = "CT", "OTHER"
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study_uid, series_uid, \
        frame_uid
    u, w = np.array(iop[:3]), np.array(iop[3:])
    n = np.cross(u, w)
    ds.ImageOrientationPatient = list(iop)
    ds.ImagePositionPatient = (np.asarray(origin) + k * spacing[2] * n).tolist()
    ds.PixelSpacing = [spacing[1], spacing[0]]
    ds.Rows, ds.Columns = pixels.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.RescaleSlope, ds.RescaleIntercept = 2, -1000
    ds.PixelData = pixels.astype(np.int16).tobytes()
    return ds


def write_sphere_series(folder, *, radius=12.0, centre=(5.0, -3.0, 40.0), spacing=(0.9, 0.7, 1.1),
                        shape=(40, 44, 36), seed=1, names=None):
    """An air sphere in tissue, oriented with rows along -y (IOP 1,0,0 / 0,-1,0: slices run
    along -z), files named in shuffled order. Returns the file paths."""
    iop = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0)
    u, w = np.array(iop[:3]), np.array(iop[3:])
    n = np.cross(u, w)
    nk, nj, ni = shape
    c = np.asarray(centre)
    origin = c - (ni / 2) * spacing[0] * u - (nj / 2) * spacing[1] * w - (nk / 2) * spacing[2] * n
    k, j, i = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
    p = (origin + i[..., None] * spacing[0] * u + j[..., None] * spacing[1] * w
         + k[..., None] * spacing[2] * n)
    r = np.linalg.norm(p - c, axis=-1)
    step = np.min(spacing)
    air = np.clip(0.5 - (r - radius) / step, 0.0, 1.0)  # a linear partial-volume ramp
    hu = air * -1000.0 + (1 - air) * 40.0
    stored = np.rint((hu + 1000.0) / 2.0)
    ids = dict(series_uid=generate_uid(), study_uid=generate_uid(), frame_uid=generate_uid())
    order = np.random.default_rng(seed).permutation(nk)
    paths = []
    for rank, kk in enumerate(order):
        ds = _slice(kk, stored[kk], spacing=spacing, origin=origin, iop=iop, **ids)
        path = folder / (names[rank] if names else f"IM{rank:05d}")
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return paths


def test_a_series_written_by_other_code_reads_back_to_its_surface(tmp_path):
    write_sphere_series(tmp_path)
    vol = read_dicom_series(tmp_path)
    np.testing.assert_allclose(vol.spacing, [0.9, 0.7, 1.1], atol=1e-9)
    mesh, info = air_surface(vol, -500.0)
    r = np.linalg.norm(mesh.vertices * 1e3 - [5.0, -3.0, 40.0], axis=1)
    assert np.max(np.abs(r - 12.0)) < 0.35  # the iso-surface of the ramp, to a fraction of a voxel
    assert mesh.volume < 0 and info["components"] == 1


def _copy_series(src, dst):
    dst.mkdir()
    for p in sorted(src.iterdir()):
        (dst / p.name).write_bytes(p.read_bytes())
    return sorted(dst.iterdir())


def test_bad_series_are_input_errors_naming_the_file(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    write_sphere_series(src, shape=(6, 20, 20))

    d = tmp_path / "missing"
    files = _copy_series(src, d)
    positions = sorted(files, key=lambda p: pydicom.dcmread(p).ImagePositionPatient[2])
    positions[2].unlink()
    with pytest.raises(InputError, match="missing slice"):
        read_dicom_series(d)

    d = tmp_path / "mixed"
    files = _copy_series(src, d)
    ds = pydicom.dcmread(files[3])
    ds.SeriesInstanceUID = generate_uid()
    ds.save_as(files[3])
    with pytest.raises(InputError, match=f"{files[3].name}.*series .* mixed"):
        read_dicom_series(d)

    d = tmp_path / "notdicom"
    files = _copy_series(src, d)
    (d / "notes.txt").write_text("not an image")
    with pytest.raises(InputError, match="notes.txt: not a DICOM file"):
        read_dicom_series(d)

    d = tmp_path / "modality"
    files = _copy_series(src, d)
    ds = pydicom.dcmread(files[0])
    ds.Modality = "MR"
    ds.save_as(files[0])
    with pytest.raises(InputError, match=f"{files[0].name}: modality 'MR'"):
        read_dicom_series(d)

    d = tmp_path / "single"
    files = _copy_series(src, d)
    for p in files[1:]:
        p.unlink()
    with pytest.raises(InputError, match=f"{files[0].name}: a single 2D image"):
        read_dicom_series(d)

    d = tmp_path / "tilt"
    files = _copy_series(src, d)
    for p in files:  # shear the positions along y with z: a tilted gantry
        ds = pydicom.dcmread(p)
        x, y, z = (float(c) for c in ds.ImagePositionPatient)
        ds.ImagePositionPatient = [x, y + 0.3 * z, z]
        ds.save_as(p)
    with pytest.raises(InputError, match="gantry tilt"):
        read_dicom_series(d)

    d = tmp_path / "tilt_tag"
    files = _copy_series(src, d)
    ds = pydicom.dcmread(files[1])
    ds.GantryDetectorTilt = 12.0
    ds.save_as(files[1])
    with pytest.raises(InputError, match=f"{files[1].name}: gantry tilt 12"):
        read_dicom_series(d)


def test_distance_to_polyline_is_exact():
    line = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])
    pts = np.array([[0.5, 0.3, 0], [2, 2, 0], [-1, 0, 1], [1.2, 0.5, 0]])
    np.testing.assert_allclose(distance_to_polyline(pts, line),
                               [0.3, np.sqrt(2), np.sqrt(2), 0.2])


def test_nifti_reads_back_to_its_surface_and_2d_inputs_are_refused(tmp_path):
    import nibabel as nib

    from implantplan.systems.anatomy.cbct import read_volume

    # the sphere of air in LPS, written with a RAS affine as NIfTI files are
    h, c, radius = 0.8, np.array([4.0, -2.0, 30.0]), 10.0
    n = 36
    ijk = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), axis=-1).astype(float)
    ras_affine = np.diag([h, h, h, 1.0])
    ras_affine[:3, 3] = [-c[0] - n * h / 2, -c[1] - n * h / 2, c[2] - n * h / 2]
    ras = ijk @ ras_affine[:3, :3].T + ras_affine[:3, 3]
    lps = ras * [-1, -1, 1]
    r = np.linalg.norm(lps - c, axis=-1)
    air = np.clip(0.5 - (r - radius) / h, 0, 1)
    nib.save(nib.Nifti1Image((air * -1000 + (1 - air) * 40).astype(np.float32), ras_affine),
             tmp_path / "ct.nii.gz")
    vol = read_volume(tmp_path / "ct.nii.gz")
    mesh, _ = air_surface(vol, -500.0)
    rr = np.linalg.norm(mesh.vertices * 1e3 - c, axis=1)
    assert np.max(np.abs(rr - radius)) < 0.35
    nib.save(nib.Nifti1Image(np.zeros((20, 20), np.float32), np.eye(4)), tmp_path / "flat.nii")
    with pytest.raises(InputError, match="flat.nii: image of shape .20, 20.; expected a 3D"):
        read_volume(tmp_path / "flat.nii")
    (tmp_path / "s").mkdir()
    one = write_sphere_series(tmp_path / "s", shape=(3, 8, 8))
    with pytest.raises(InputError, match="one DICOM file .a 2D image."):
        read_volume(one[0])


def test_a_compressed_volume_counts_its_voxels_from_the_header(tmp_path):
    """A .nii.gz of zeros is far smaller than its voxels (the memory estimate once counted
    voxels from the file's size, 2 bytes each, and let a 1.4 MB file of 149 M voxels through);
    the header gives the shape. A DICOM folder: slices x rows x columns."""
    import nibabel as nib

    from implantplan.systems.anatomy.cbct import volume_voxels

    path = tmp_path / "zeros.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros((200, 150, 60), np.int16), np.eye(4)), path)
    assert path.stat().st_size / 2 < 0.05 * 200 * 150 * 60
    assert volume_voxels(path) == 200 * 150 * 60
    assert volume_voxels(tmp_path / "missing.nii.gz") is None
    folder = tmp_path / "series"
    write_ct_series(folder, np.zeros((4, 12, 10), np.float32), [0.0, 0.0, 0.0],
                    [0.5, 0.5, 0.5], ids=SeriesIds())
    assert volume_voxels(folder) == 4 * 12 * 10
