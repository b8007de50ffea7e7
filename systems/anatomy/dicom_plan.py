"""DICOM out (DESIGN.md section 12): the plan as an Implantation Plan SR (SOP class
1.2.840.10008.5.1.4.1.1.88.70, root template TID 7000) that references Encapsulated STL instances
(1.2.840.10008.5.1.4.1.1.104.3) of the scan and of each planned implant; written with pydicom.

The SR's root CONTAINER is (112345, DCM, "Implantation Plan") with TID 7000 in its Content
Template Sequence. It CONTAINS "Information used for planning" (112358, DCM): a COMPOSITE
reference to the scan's STL; and per implant a "Selected Implant Component" (112346, DCM)
CONTAINER with the site (TEXT, its FDI tooth), a COMPOSITE reference to the implant's STL and
the geometry as NUM items in mm (UCUM): entry point x, y, z, axis x, y, z (unit vector, "1"),
diameter and length, coded in this project's private scheme 99IMPLANTPLAN (TID 7000 carries no
SCOORD3D: the geometry travels in the STL, the NUMs let any SR reader take the numbers back).
Coordinates are in the case's mesh frame = DICOM's patient frame (LPS, mm) for a CBCT case; the
Frame of Reference UID is the input series' when there is one. Entry point = the implant's
platform on the jaw surface (the site), axis from the bone into the cavity, apex = entry -
length * axis.

The implant STL is a closed cylinder (trimesh) of the implant's diameter and length from the
apex to the entry point; the scan STL is the surface the plan was made on.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

IMPLANTATION_PLAN_SR = "1.2.840.10008.5.1.4.1.1.88.70"
ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"
SCHEME = "99IMPLANTPLAN"
GEOMETRY_CODES = {  # NUM concept -> (code value, meaning, UCUM unit)
    "entry_x": ("IP001", "Implant entry point x (LPS)", "mm"),
    "entry_y": ("IP002", "Implant entry point y (LPS)", "mm"),
    "entry_z": ("IP003", "Implant entry point z (LPS)", "mm"),
    "axis_x": ("IP004", "Implant axis x (LPS)", "1"),
    "axis_y": ("IP005", "Implant axis y (LPS)", "1"),
    "axis_z": ("IP006", "Implant axis z (LPS)", "1"),
    "diameter": ("IP007", "Implant diameter", "mm"),
    "length": ("IP008", "Implant length", "mm"),
}


@dataclass(frozen=True)
class PlannedImplant:
    """One implant in the mesh frame (m): site name, entry point, unit axis (bone -> cavity),
    diameter and length."""

    site: str
    entry: np.ndarray
    axis: np.ndarray
    diameter: float
    length: float


@dataclass(frozen=True)
class StudyIds:
    """Patient and study identifiers (from the input series, or the case's keys)."""

    patient_id: str
    patient_name: str
    study_uid: str
    study_id: str = "1"
    accession_number: str = ""
    frame_uid: str | None = None


def implant_mesh(implant: PlannedImplant, *, sections: int = 48) -> trimesh.Trimesh:
    """A closed cylinder (m) from the apex to the entry point."""
    from implantplan.systems.frames import frame_from_z

    mid = implant.entry - 0.5 * implant.length * implant.axis
    return trimesh.creation.cylinder(radius=implant.diameter / 2, height=implant.length,
                                     sections=sections, transform=frame_from_z(mid, implant.axis))


def _code(value: str, scheme: str, meaning: str):
    from pydicom.dataset import Dataset

    c = Dataset()
    c.CodeValue, c.CodingSchemeDesignator, c.CodeMeaning = value, scheme, meaning
    return c


def _common(ds, ids: StudyIds, *, sop_class: str, modality: str, series_uid: str, number: int,
            now: datetime.datetime) -> None:
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, meta.MediaStorageSOPInstanceUID
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.PatientID, ds.PatientName = ids.patient_id, ids.patient_name
    ds.PatientBirthDate, ds.PatientSex = "", ""
    ds.StudyInstanceUID, ds.StudyID = ids.study_uid, ids.study_id
    ds.AccessionNumber, ds.ReferringPhysicianName = ids.accession_number, ""
    ds.StudyDate, ds.StudyTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ds.ContentDate, ds.ContentTime = ds.StudyDate, ds.StudyTime
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = modality, series_uid, number
    ds.InstanceNumber = 1
    ds.Manufacturer, ds.ManufacturerModelName = "implantplan", "implantplan"
    ds.DeviceSerialNumber, ds.SoftwareVersions = "0", "implantplan"


def _stl_instance(mesh_m: trimesh.Trimesh, title: str, ids: StudyIds, frame_uid: str, *,
                  number: int, now):
    """An Encapsulated STL instance of a mesh (mm)."""
    from pydicom.dataset import Dataset
    from pydicom.uid import generate_uid

    ds = Dataset()
    _common(ds, ids, sop_class=ENCAPSULATED_STL, modality="M3D", series_uid=generate_uid(),
            number=number, now=now)
    ds.FrameOfReferenceUID = frame_uid
    ds.PositionReferenceIndicator = ""
    ds.AcquisitionDateTime = now.strftime("%Y%m%d%H%M%S")
    ds.BurnedInAnnotation = "NO"
    ds.DocumentTitle = title
    ds.ConceptNameCodeSequence = []
    ds.MIMETypeOfEncapsulatedDocument = "model/stl"
    ds.MeasurementUnitsCodeSequence = [_code("mm", "UCUM", "millimeter")]
    mm = mesh_m.copy()
    mm.apply_scale(1e3)
    data = trimesh.exchange.stl.export_stl(mm)
    if len(data) % 2:
        data += b"\0"
    ds.EncapsulatedDocument = data
    ds.EncapsulatedDocumentLength = len(data)
    return ds


def _item(relationship: str, value_type: str, concept):
    from pydicom.dataset import Dataset

    it = Dataset()
    it.RelationshipType, it.ValueType = relationship, value_type
    it.ConceptNameCodeSequence = [concept]
    return it


def _num(name: str, value: float):
    from pydicom.dataset import Dataset

    code, meaning, unit = GEOMETRY_CODES[name]
    it = _item("CONTAINS", "NUM", _code(code, SCHEME, meaning))
    mv = Dataset()
    mv.NumericValue = f"{value:.10g}"[:16]
    mv.MeasurementUnitsCodeSequence = [_code(unit, "UCUM", "millimeter" if unit == "mm"
                                             else "no units")]
    it.MeasuredValueSequence = [mv]
    return it


def _composite(concept, ds_ref):
    from pydicom.dataset import Dataset

    it = _item("CONTAINS", "COMPOSITE", concept)
    ref = Dataset()
    ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID = ds_ref.SOPClassUID, \
        ds_ref.SOPInstanceUID
    it.ReferencedSOPSequence = [ref]
    return it


def write_dicom_plan(folder, scan_m: trimesh.Trimesh, implants: list[PlannedImplant],
                     ids: StudyIds, *, title: str = "implantplan implant plan") -> dict:
    """Write ``plan.dcm`` (the SR), ``scan_stl.dcm`` and ``implant_<site>.dcm`` (Encapsulated
    STL), and ``implant_<site>.stl`` into ``folder``; return the file names."""
    from pydicom.dataset import Dataset
    from pydicom.uid import generate_uid

    folder = Path(folder)
    now = datetime.datetime.now(datetime.timezone.utc)
    frame_uid = ids.frame_uid or str(generate_uid())
    scan = _stl_instance(scan_m, "scan surface", ids, frame_uid, number=101, now=now)
    scan.save_as(folder / "scan_stl.dcm", enforce_file_format=True)
    files = {"sr": "plan.dcm", "scan_stl": "scan_stl.dcm", "implants": []}
    sr = Dataset()
    _common(sr, ids, sop_class=IMPLANTATION_PLAN_SR, modality="SR", series_uid=generate_uid(),
            number=100, now=now)
    sr.ValueType = "CONTAINER"
    sr.ConceptNameCodeSequence = [_code("112345", "DCM", "Implantation Plan")]
    sr.ContinuityOfContent = "SEPARATE"
    tpl = Dataset()
    tpl.MappingResource, tpl.TemplateIdentifier = "DCMR", "7000"
    sr.ContentTemplateSequence = [tpl]
    sr.CompletionFlag, sr.VerificationFlag = "COMPLETE", "UNVERIFIED"
    sr.SeriesDescription = title
    sr.ReferencedPerformedProcedureStepSequence = []
    sr.PerformedProcedureCodeSequence = []
    content = [_composite(_code("112358", "DCM", "Information used for planning"), scan)]
    refs = [scan]
    for k, imp in enumerate(implants):
        stl = _stl_instance(implant_mesh(imp), f"implant {imp.site}", ids, frame_uid,
                            number=102 + k, now=now)
        name = f"implant_{imp.site}"
        stl.save_as(folder / f"{name}.dcm", enforce_file_format=True)
        implant_mesh(imp).apply_scale(1e3).export(folder / f"{name}.stl")
        files["implants"].append({"site": imp.site, "dcm": f"{name}.dcm", "stl": f"{name}.stl"})
        refs.append(stl)
        box = _item("CONTAINS", "CONTAINER", _code("112346", "DCM", "Selected Implant Component"))
        box.ContinuityOfContent = "SEPARATE"
        site = _item("CONTAINS", "TEXT", _code("IP000", SCHEME, "Implant site (FDI tooth)"))
        site.TextValue = imp.site
        values = {"entry_x": imp.entry[0] * 1e3, "entry_y": imp.entry[1] * 1e3,
                  "entry_z": imp.entry[2] * 1e3, "axis_x": imp.axis[0], "axis_y": imp.axis[1],
                  "axis_z": imp.axis[2], "diameter": imp.diameter * 1e3,
                  "length": imp.length * 1e3}
        box.ContentSequence = [site, _composite(_code("112348", "DCM", "Implant Template"), stl),
                               *(_num(n, v) for n, v in values.items())]
        content.append(box)
    sr.ContentSequence = content
    evidence = Dataset()
    evidence.StudyInstanceUID = ids.study_uid
    series = []
    for r in refs:
        s = Dataset()
        s.SeriesInstanceUID = r.SeriesInstanceUID
        ref = Dataset()
        ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID = r.SOPClassUID, r.SOPInstanceUID
        s.ReferencedSOPSequence = [ref]
        series.append(s)
    evidence.ReferencedSeriesSequence = series
    sr.CurrentRequestedProcedureEvidenceSequence = [evidence]
    sr.save_as(folder / "plan.dcm", enforce_file_format=True)
    return files


def read_dicom_plan(path) -> list[dict]:
    """The implants of a ``plan.dcm`` (site, entry m, axis, diameter m, length m)."""
    import pydicom

    ds = pydicom.dcmread(path)
    by_code = {v[0]: k for k, v in GEOMETRY_CODES.items()}
    out = []
    for box in ds.ContentSequence:
        if box.ConceptNameCodeSequence[0].CodeValue != "112346":
            continue
        rec = {}
        for it in box.ContentSequence:
            code = it.ConceptNameCodeSequence[0].CodeValue
            if it.ValueType == "TEXT":
                rec["site"] = str(it.TextValue)
            elif it.ValueType == "NUM" and code in by_code:
                rec[by_code[code]] = float(it.MeasuredValueSequence[0].NumericValue)
        out.append({"site": rec["site"],
                    "entry": np.array([rec["entry_x"], rec["entry_y"], rec["entry_z"]]) * 1e-3,
                    "axis": np.array([rec["axis_x"], rec["axis_y"], rec["axis_z"]]),
                    "diameter": rec["diameter"] * 1e-3, "length": rec["length"] * 1e-3})
    return out
