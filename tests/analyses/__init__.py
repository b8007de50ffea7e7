"""Tests of implantplan.analyses."""
