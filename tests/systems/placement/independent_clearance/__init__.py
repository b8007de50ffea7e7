"""An independent check of the sound tool clearance (systems.placement.tool_clearance), written
apart
from it: its own FPSM geometry and FCL ground truth (groundtruth.py), adversarial rod families
(harness.py)."""
