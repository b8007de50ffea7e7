"""Stage 5, the feeding simulation: every LeafSystem of the teleop diagram (master inputs,
fixture, supervisor, FPSM estimator, head motion, tracker, head guard, adversarial operator)."""
