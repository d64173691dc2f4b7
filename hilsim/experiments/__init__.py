"""The seed paper's experiments, reproduced in simulation (``hilsim experiment NAME``).

- :mod:`hilsim.experiments.water_tank`: the run through positions A, B, C (sections 3-4, Fig. 4);
- :mod:`hilsim.experiments.control`: the track controller that drives it;
- :mod:`hilsim.experiments.tank_geometry`: which cuboid faces each position should show;
- :mod:`hilsim.experiments.sampling`: the paper's 96 x 1000 sampling against the artifact-free one.

The command itself, and the files it writes, are in :mod:`hilsim.experiment`.
"""
