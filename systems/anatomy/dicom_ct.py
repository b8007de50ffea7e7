"""Writing a CT volume as a DICOM CT Image Storage series (pydicom), one file per axial slice.

The volume ``hu[k, j, i]`` is written with ImageOrientationPatient (1, 0, 0, 0, 1, 0) (columns
along patient x, rows along y, slices along z, LPS), ImagePositionPatient of each slice's first
voxel, PixelSpacing (row, column) and SliceThickness / SpacingBetweenSlices the voxel size, stored
unsigned (HU + 1024) with RescaleIntercept -1024, RescaleSlope 1, as scanners do. Identifiers
(patient, study, series, frame of reference) are the caller's or new UIDs.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


@dataclass(frozen=True)
class SeriesIds:
    """Identifiers written into every slice (new UIDs by default)."""

    patient_id: str = "IMPLANTPLAN-PHANTOM"
    patient_name: str = "Phantom^Implantplan"
    study_id: str = "1"
    study_uid: str = field(default_factory=lambda: _uid())
    series_uid: str = field(default_factory=lambda: _uid())
    frame_uid: str = field(default_factory=lambda: _uid())
    description: str = "implantplan synthetic CBCT phantom"


def _uid() -> str:
    from pydicom.uid import generate_uid

    return str(generate_uid())


def write_ct_series(folder, hu: np.ndarray, origin_mm, spacing_mm, *, ids: SeriesIds,
                    prefix: str = "CT") -> list[Path]:
    """Write ``hu`` [k, j, i] (HU) as slices ``{prefix}{k:04d}.dcm`` in ``folder`` (created).
    ``origin_mm`` is voxel (0, 0, 0) in LPS mm, ``spacing_mm`` (di, dj, dk)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    di, dj, dk = (float(s) for s in spacing_mm)
    origin = np.asarray(origin_mm, dtype=float)
    stored = np.clip(np.rint(hu) + 1024, 0, 65535).astype(np.uint16)
    now = datetime.datetime.now(datetime.timezone.utc)
    date, time = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    paths = []
    for k in range(stored.shape[0]):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CT_IMAGE_STORAGE
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.PatientID, ds.PatientName = ids.patient_id, ids.patient_name
        ds.StudyInstanceUID, ds.SeriesInstanceUID = ids.study_uid, ids.series_uid
        ds.FrameOfReferenceUID, ds.StudyID = ids.frame_uid, ids.study_id
        ds.SeriesNumber, ds.InstanceNumber = 1, k + 1
        ds.StudyDate = ds.SeriesDate = ds.ContentDate = date
        ds.StudyTime = ds.SeriesTime = ds.ContentTime = time
        ds.SeriesDescription = ids.description
        ds.Manufacturer = "implantplan"
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [float(origin[0]), float(origin[1]), float(origin[2] + k * dk)]
        ds.SliceLocation = float(origin[2] + k * dk)
        ds.PixelSpacing = [dj, di]
        ds.SliceThickness = dk
        ds.SpacingBetweenSlices = dk
        ds.Rows, ds.Columns = int(stored.shape[1]), int(stored.shape[2])
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = -1024, 1, "HU"
        ds.KVP = 90
        ds.PixelData = stored[k].tobytes()
        path = folder / f"{prefix}{k + 1:04d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return paths
