"""CBCT volumes in: a DICOM CT series (folder) or a NIfTI file -> HU volume -> the surfaces the
planner fits (DESIGN.md section 12).

Reading (:func:`read_dicom_series`, pydicom): every file in the folder must be a DICOM CT image
of one series (one SeriesInstanceUID, one orientation, one pixel grid); the slices are sorted by
their position along the slice normal n = row x column direction (ImageOrientationPatient), the
spacing between them must be uniform (a gap is a missing slice) and their offsets must run along
n (anything else is gantry tilt, refused: resampling a tilted series is the scanner's job).
Pixel values are rescaled to HU (RescaleSlope, RescaleIntercept). The voxel (i, j, k) = (column,
row, slice) sits at ``affine @ [i, j, k, 1]`` in DICOM's patient frame (LPS, mm).
:func:`read_nifti` reads a NIfTI file with nibabel (RAS affine turned to LPS; values taken as HU).

Surfaces (:func:`air_surface`, :func:`bone_surface`; marching cubes from scikit-image): the oral
cavity is the air (HU below the case's ``air_threshold_hu``) component, 6-connected, that is
enclosed by tissue (does not touch the volume's border: the room's air around the head does),
the largest such; with none enclosed, the largest component. Its iso-surface at the threshold
is extracted from the HU values (sub-voxel, linear interpolation between voxel centres), with
the other air components masked out, and oriented as the bundled scan is (normals into the
cavity). The bone surface is the iso-surface at ``bone_threshold_hu`` of the largest bone
component. Both are returned in metres in the patient frame: the case's frames are DICOM's
patient frame (LPS), so the case's ``center`` and sites are written in LPS mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.oral_mesh import validate_mesh

NIFTI_SUFFIXES = (".nii", ".nii.gz")
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
MAX_VOXELS = 200_000_000  # a volume read must fit (float32: 800 MB), checked before pixels load
MAX_FILES = 4000  # slices in one series
FRAME_NOTE = "DICOM patient frame (LPS, mm); the case's mesh frame is this frame (identity)"


@dataclass
class Volume:
    """A CT volume: ``hu`` indexed [k, j, i] (slice, row, column), float32 HU; ``affine`` maps
    (i, j, k, 1) to LPS mm; ``info`` the series identifiers and geometry (JSON-ready)."""

    hu: np.ndarray
    affine: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size (mm) along i, j, k."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def to_patient(self, ijk: np.ndarray) -> np.ndarray:
        """(n, 3) voxel coordinates (i, j, k) -> (n, 3) LPS mm."""
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]


def is_dicom_file(path) -> bool:
    """A file with DICOM's preamble ("DICM" at byte 128)."""
    try:
        with open(path, "rb") as f:
            return f.read(132)[128:] == b"DICM"
    except OSError:
        return False


def is_volume_path(path) -> bool:
    """True when a scan path names a CBCT (a folder, a NIfTI file, or one DICOM file, which is
    refused as a 2D image), not a mesh."""
    path = Path(path)
    return (path.is_dir() or path.name.lower().endswith(NIFTI_SUFFIXES)
            or (path.is_file() and is_dicom_file(path)))


def scan_files(path) -> list[Path]:
    """The files a scan path stands for (provenance hashes them): the file, or a series folder's
    files in name order."""
    path = Path(path)
    if path.is_dir():
        return sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    return [path]


def volume_voxels(path) -> int | None:
    """The voxels a CBCT path holds, from its headers alone (no pixel data read): a NIfTI
    file's shape, or a series folder's slice count times its first slice's rows and columns;
    None where the headers cannot tell (the reader then names what is wrong). A compressed
    file holds far more voxels than its size says."""
    path = Path(path)
    try:
        if path.is_dir():
            import pydicom

            files = scan_files(path)
            if not files:
                return None
            ds = pydicom.dcmread(files[0], stop_before_pixels=True)
            return len(files) * int(ds.Rows) * int(ds.Columns)
        if path.name.lower().endswith(NIFTI_SUFFIXES):
            import nibabel as nib

            return int(np.prod(nib.load(str(path)).header.get_data_shape()))
    except Exception:  # an unreadable header: the reader's own error says what is wrong
        return None
    return None


def read_volume(path, *, field: str = "mesh.path") -> Volume:
    """A DICOM series folder or a NIfTI file as a :class:`Volume`."""
    path = Path(path)
    if path.is_dir():
        return read_dicom_series(path, field=field)
    if is_dicom_file(path):
        raise _bad(field, path, "one DICOM file (a 2D image); expected the folder of its CT "
                   "series")
    return read_nifti(path, field=field)


def _bad(field: str, path: Path, message: str) -> InputError:
    return InputError(field, f"{path}: {message}")


def _header(path: Path, field: str):
    import pydicom
    from pydicom.errors import InvalidDicomError

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except InvalidDicomError:
        raise _bad(field, path, "not a DICOM file (expected only CT slices of one series in "
                   "the folder)") from None
    except OSError as e:
        raise _bad(field, path, f"cannot be read ({e.strerror or e})") from None
    modality = ds.get("Modality")
    if modality != "CT":
        raise _bad(field, path, f"modality {modality!r}, expected 'CT' (a CT or CBCT series)")
    for key in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "Rows",
                "Columns", "SeriesInstanceUID"):
        if key not in ds:
            raise _bad(field, path, f"has no {key} (expected a CT image slice)")
    if int(ds.get("NumberOfFrames", 1) or 1) > 1:
        raise _bad(field, path, "is a multi-frame image; expected one slice per file")
    tilt = float(ds.get("GantryDetectorTilt", 0.0) or 0.0)
    if abs(tilt) > 1e-6:
        raise _bad(field, path, f"gantry tilt {tilt:g} deg; expected 0 (resample the series "
                   "on the scanner first)")
    return ds


def read_dicom_series(folder, *, field: str = "mesh.path") -> Volume:
    """Read one CT series from a folder (every regular, non-hidden file in it); see the module
    docstring for the checks. Errors name the file and what was expected (exit 2)."""
    import pydicom

    folder = Path(folder)
    files = scan_files(folder)
    if not files:
        raise InputError(field, f"{folder}: the folder holds no DICOM files")
    if len(files) > MAX_FILES:
        raise InputError(field, f"{folder}: {len(files)} files, at most {MAX_FILES} slices")
    headers = [_header(p, field) for p in files]
    first = headers[0]
    if len(headers) == 1:
        raise _bad(field, files[0], "a single 2D image; expected a CT series of at least two "
                   "slices (a volume)")
    iop = np.array(first.ImageOrientationPatient, dtype=float)
    grid = (int(first.Rows), int(first.Columns), tuple(float(s) for s in first.PixelSpacing))
    for p, ds in zip(files, headers, strict=True):
        if ds.SeriesInstanceUID != first.SeriesInstanceUID:
            raise _bad(field, p, f"series {ds.SeriesInstanceUID} mixed with series "
                       f"{first.SeriesInstanceUID} of {files[0].name}; expected one series per "
                       "folder")
        if not np.allclose(np.array(ds.ImageOrientationPatient, dtype=float), iop, atol=1e-4):
            raise _bad(field, p, "orientation differs from the series' first slice")
        g = (int(ds.Rows), int(ds.Columns), tuple(float(s) for s in ds.PixelSpacing))
        if g[:2] != grid[:2] or not np.allclose(g[2], grid[2], rtol=1e-6):
            raise _bad(field, p, f"pixel grid {g} differs from the series' {grid}")
    rows, cols, (d_row, d_col) = grid
    if len(files) * rows * cols > MAX_VOXELS:
        raise InputError(field, f"{folder}: {len(files)} x {rows} x {cols} voxels, at most "
                         f"{MAX_VOXELS:,}")
    u, w = iop[:3], iop[3:]  # direction of increasing column index, of increasing row index
    if abs(np.linalg.norm(u) - 1) > 1e-3 or abs(np.linalg.norm(w) - 1) > 1e-3 or abs(u @ w) > 1e-3:
        raise _bad(field, files[0], "ImageOrientationPatient is not two orthonormal directions")
    n = np.cross(u, w)
    pos = np.array([np.array(ds.ImagePositionPatient, dtype=float) for ds in headers])
    s = pos @ n
    order = np.argsort(s, kind="stable")
    pos, s = pos[order], s[order]
    files = [files[k] for k in order]
    steps = np.diff(s)
    if np.any(steps < 1e-6):
        k = int(np.argmin(steps))
        raise _bad(field, files[k + 1], f"lies at the same position as {files[k].name}; "
                   "expected one slice per position")
    dz = float(np.median(steps))
    bad = np.abs(steps - dz) > max(1e-3, 0.01 * dz)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        what = (f"a missing slice ({steps[k]:.4g} mm after {files[k].name}, the series' step is "
                f"{dz:.4g} mm)" if steps[k] > dz else f"an uneven step ({steps[k]:.4g} mm, "
                f"expected {dz:.4g} mm)")
        raise _bad(field, files[k + 1], what)
    lateral = (pos - pos[0]) - np.outer(s - s[0], n)
    if np.max(np.linalg.norm(lateral, axis=1)) > max(1e-3, 0.01 * dz):
        k = int(np.argmax(np.linalg.norm(lateral, axis=1)))
        raise _bad(field, files[k], "slice positions do not run along the slice normal "
                   "(gantry tilt); expected an untilted series")
    hu = np.empty((len(files), rows, cols), dtype=np.float32)
    for k, p in enumerate(files):
        ds = pydicom.dcmread(p)
        try:
            pixels = ds.pixel_array
        except Exception as e:  # a compressed transfer syntax without its decoder, truncated data
            raise _bad(field, p, f"pixel data cannot be decoded ({e})") from None
        if pixels.shape != (rows, cols):
            raise _bad(field, p, f"pixel data shape {pixels.shape}, expected ({rows}, {cols})")
        slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
        intercept = float(ds.get("RescaleIntercept", 0.0) or 0.0)
        hu[k] = pixels.astype(np.float32) * slope + intercept
    affine = np.eye(4)
    affine[:3, 0], affine[:3, 1], affine[:3, 2] = u * d_col, w * d_row, n * dz
    affine[:3, 3] = pos[0]
    info = {
        "source": "dicom", "files": len(files), "shape_kji": list(hu.shape),
        "spacing_mm": [d_col, d_row, dz], "frame": FRAME_NOTE,
        "series_instance_uid": str(first.SeriesInstanceUID),
        "study_instance_uid": str(first.get("StudyInstanceUID", "")),
        "frame_of_reference_uid": str(first.get("FrameOfReferenceUID", "")),
        "patient_id": str(first.get("PatientID", "")),
        "patient_name": str(first.get("PatientName", "")),
        "study_id": str(first.get("StudyID", "")),
        "accession_number": str(first.get("AccessionNumber", "")),
        "sop_class_uid": str(first.get("SOPClassUID", "")),
    }
    return Volume(hu, affine, info)


def read_nifti(path, *, field: str = "mesh.path") -> Volume:
    """A 3D NIfTI file (nibabel) as a :class:`Volume`; values are taken as HU."""
    import nibabel as nib

    path = Path(path)
    try:
        img = nib.load(str(path))
    except Exception as e:  # nibabel raises ImageFileError, OSError, EOFError, ...
        raise _bad(field, path, f"not a readable NIfTI file ({e})") from None
    shape = tuple(int(d) for d in img.shape)
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) != 3 or min(shape) < 2:
        raise _bad(field, path, f"image of shape {shape}; expected a 3D volume (a 2D image or "
                   "a time series is not a CBCT)")
    if int(np.prod(shape)) > MAX_VOXELS:
        raise _bad(field, path, f"{int(np.prod(shape)):,} voxels, at most {MAX_VOXELS:,}")
    data = np.asarray(img.dataobj, dtype=np.float32).reshape(shape)
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ img.affine  # RAS -> LPS
    info = {"source": "nifti", "shape_kji": list(shape[::-1]),
            "spacing_mm": np.linalg.norm(affine[:3, :3], axis=0).tolist(), "frame": FRAME_NOTE}
    return Volume(np.ascontiguousarray(data.transpose(2, 1, 0)), affine, info)


def _component(mask: np.ndarray, *, enclosed: bool) -> tuple[np.ndarray, dict]:
    """The largest 6-connected component of ``mask`` (enclosed: not touching the border, when
    one is)."""
    from scipy import ndimage

    labels, count = ndimage.label(mask)
    if count == 0:
        return np.zeros_like(mask), {"components": 0}
    sizes = np.bincount(labels.ravel())[1:]
    candidates = np.arange(1, count + 1)
    if enclosed:
        border = np.unique(np.concatenate([
            labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(), labels[:, :, [0, -1]].ravel()]))
        inner = np.setdiff1d(candidates, border)
        if inner.size:
            candidates = inner
    best = candidates[np.argmax(sizes[candidates - 1])]
    return labels == best, {"components": int(count), "voxels": int(sizes[best - 1]),
                            "touches_border": bool(best not in candidates) if enclosed else None}


def _iso_surface(volume: Volume, field_kji: np.ndarray, level: float) -> trimesh.Trimesh:
    """Marching cubes of ``field_kji`` at ``level`` -> a mesh in LPS mm (padded by one voxel of
    the field's high side so the surface closes)."""
    from skimage.measure import marching_cubes

    high = float(max(np.max(field_kji), level + 1.0))
    padded = np.pad(field_kji, 1, constant_values=high)
    verts, faces, _, _ = marching_cubes(padded, level=level, allow_degenerate=False)
    kji = verts - 1.0
    mesh = trimesh.Trimesh(volume.to_patient(kji[:, ::-1]), faces[:, ::-1], process=True)
    return mesh


def air_surface(volume: Volume, threshold_hu: float, *, field: str = "mesh.path"):
    """The oral cavity's air/tissue boundary (m, LPS), normals into the cavity; and its info."""
    air = volume.hu < threshold_hu
    cavity, info = _component(air, enclosed=True)
    if not cavity.any():
        raise InputError(field, f"no voxel below mesh.air_threshold_hu = {threshold_hu:g} HU: "
                         "no air cavity in the volume")
    from scipy import ndimage

    # other air stays out of the surface: outside a 2-voxel band around the cavity, tissue HU
    near = ndimage.binary_dilation(cavity, iterations=2)
    keep = near & ~(air & ~cavity)
    fieldv = np.where(keep, volume.hu, np.float32(threshold_hu + 500.0))
    mesh = _iso_surface(volume, fieldv, threshold_hu)
    mesh.apply_scale(1e-3)
    if mesh.volume > 0:  # the bundled scan is seen from the inside (negative signed volume)
        mesh.invert()
    info.update({"threshold_hu": float(threshold_hu), "faces": int(len(mesh.faces))})
    return mesh, info


def bone_surface(volume: Volume, threshold_hu: float):
    """The bone iso-surface (m, LPS) of the largest component above ``threshold_hu``, normals
    out of the bone; None when the volume has no bone."""
    bone, info = _component(volume.hu >= threshold_hu, enclosed=False)
    if not bone.any():
        return None, info
    low = np.float32(threshold_hu - 500.0)
    mesh = _iso_surface(volume, np.where(bone, -volume.hu, -low), -threshold_hu)
    mesh.apply_scale(1e-3)
    if mesh.volume < 0:
        mesh.invert()
    info.update({"threshold_hu": float(threshold_hu), "faces": int(len(mesh.faces))})
    return mesh, info


@dataclass
class CbctScan:
    """A CBCT as the planner's scan: ``mesh`` the air/tissue surface (m, LPS, validated as meshes
    are), ``bone`` the bone surface (m, LPS; None without bone), ``volume`` the HU volume and
    ``info`` (JSON-ready: the series, both surfaces, the frame statement)."""

    mesh: trimesh.Trimesh
    bone: trimesh.Trimesh | None
    volume: Volume
    info: dict


def load_cbct_scan(path, *, air_threshold_hu: float, bone_threshold_hu: float,
                   field: str = "mesh.path") -> CbctScan:
    """Read a CBCT (:func:`read_volume`) and extract its surfaces (:func:`air_surface`,
    :func:`bone_surface`); ``mesh.metadata["implantplan"]["cbct"]`` carries ``info``."""
    volume = read_volume(path, field=field)
    raw, air_info = air_surface(volume, air_threshold_hu, field=field)
    bone, bone_info = bone_surface(volume, bone_threshold_hu)
    mesh = validate_mesh(raw, field=field)
    info = {**volume.info, "air": air_info, "bone": bone_info}
    mesh.metadata["implantplan"].update({"source": str(path), "units": "mm", "cbct": info})
    return CbctScan(mesh, bone, volume, info)
