"""Tests of implantplan.systems."""
