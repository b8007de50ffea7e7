"""Stage 3, the robot base: AUBO-i10 kinematics, arm collision, the scenario, MOPRP and NSGA-II."""
