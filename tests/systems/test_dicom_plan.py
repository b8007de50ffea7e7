"""plan.dcm (systems.anatomy.dicom_plan): an Implantation Plan SR that pydicom and DCMTK parse,
naming its SOP class and TID 7000, referencing Encapsulated STLs of the scan and each implant,
and giving back every implant's entry point, axis and size to 1e-6 m."""

from __future__ import annotations

import io
import shutil
import subprocess

import numpy as np
import pydicom
import pytest
import trimesh

from implantplan.systems.anatomy.dicom_plan import (
    ENCAPSULATED_STL,
    IMPLANTATION_PLAN_SR,
    PlannedImplant,
    StudyIds,
    implant_mesh,
    read_dicom_plan,
    write_dicom_plan,
)


def _implants(seed=0, n=3):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        axis = rng.normal(size=3)
        out.append(PlannedImplant(site=str(36 + k), entry=rng.uniform(-0.2, 0.2, 3),
                                  axis=axis / np.linalg.norm(axis),
                                  diameter=rng.uniform(3e-3, 6e-3),
                                  length=rng.uniform(6e-3, 16e-3)))
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plan")
    implants = _implants()
    ids = StudyIds(patient_id="P-7", patient_name="Doe^Jane", study_uid="1.2.826.0.1.3680043.8.1",
                   frame_uid="1.2.826.0.1.3680043.8.2")
    files = write_dicom_plan(folder, trimesh.creation.icosphere(radius=0.03), implants, ids)
    return folder, files, implants


def test_round_trip_of_entry_axis_and_size(written):
    folder, _, implants = written
    back = read_dicom_plan(folder / "plan.dcm")
    assert [b["site"] for b in back] == [i.site for i in implants]
    for b, i in zip(back, implants, strict=True):
        np.testing.assert_allclose(b["entry"], i.entry, atol=1e-6, rtol=0)
        np.testing.assert_allclose(b["axis"], i.axis, atol=1e-6, rtol=0)
        assert abs(b["diameter"] - i.diameter) < 1e-6 and abs(b["length"] - i.length) < 1e-6


def test_pydicom_reads_the_sop_class_template_and_references(written):
    folder, files, implants = written
    sr = pydicom.dcmread(folder / "plan.dcm")
    assert sr.SOPClassUID == IMPLANTATION_PLAN_SR and sr.Modality == "SR"
    assert sr.ContentTemplateSequence[0].TemplateIdentifier == "7000"
    assert sr.ConceptNameCodeSequence[0].CodeValue == "112345"
    assert sr.PatientID == "P-7" and sr.StudyInstanceUID == "1.2.826.0.1.3680043.8.1"
    referenced = {r.ReferencedSOPInstanceUID
                  for s in sr.CurrentRequestedProcedureEvidenceSequence[0].ReferencedSeriesSequence
                  for r in s.ReferencedSOPSequence}
    stls = [folder / files["scan_stl"]] + [folder / f["dcm"] for f in files["implants"]]
    assert referenced == {pydicom.dcmread(p).SOPInstanceUID for p in stls}
    for p, imp in zip(stls[1:], implants, strict=True):
        ds = pydicom.dcmread(p)
        assert ds.SOPClassUID == ENCAPSULATED_STL and ds.MIMETypeOfEncapsulatedDocument == \
            "model/stl" and ds.FrameOfReferenceUID == "1.2.826.0.1.3680043.8.2"
        mesh = trimesh.load(io.BytesIO(bytes(ds.EncapsulatedDocument)), file_type="stl")
        # the cylinder's axis ends are the apex and the entry point (mm)
        along = (mesh.vertices * 1e-3 - imp.entry) @ imp.axis
        assert along.max() == pytest.approx(0.0, abs=1e-6)
        assert along.min() == pytest.approx(-imp.length, abs=1e-6)
        assert mesh.is_watertight
    assert np.isclose(implant_mesh(implants[0]).volume,
                      np.pi * (implants[0].diameter / 2) ** 2 * implants[0].length, rtol=0.01)


@pytest.mark.skipif(shutil.which("dsrdump") is None,
                    reason="DCMTK (Debian's dcmtk: dsrdump) is not installed")
def test_dcmtk_parses_the_sr_and_accepts_the_iod(written):
    folder, _, _ = written
    run = subprocess.run(["dsrdump", str(folder / "plan.dcm")], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    assert "Implantation Plan SR Document" in run.stdout
    assert not [line for line in run.stderr.splitlines() if line.startswith(("E:", "F:"))]
    assert "Selected Implant Component" in run.stdout and "Implant entry point x" in run.stdout
    run = subprocess.run(["dcmdump", str(folder / "implant_36.dcm")], capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 0 and "model/stl" in run.stdout
