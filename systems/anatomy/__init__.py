"""Clinical anatomy (DESIGN.md section 12): CBCT volumes in (DICOM series, NIfTI), the surfaces
the planner fits (the oral cavity's air/tissue boundary, bone), and the synthetic CBCT phantom
the project makes from a mesh case."""
