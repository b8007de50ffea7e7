"""Tests of implantplan.diagrams."""
