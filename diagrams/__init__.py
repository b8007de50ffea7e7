"""Builders that wire the MultibodyPlant, SceneGraph and the project's systems into Diagrams."""
