"""Stage 1, the oral cavity: the FPSM (model and fit), the scan mesh and the implant sites."""
