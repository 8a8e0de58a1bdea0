"""The appliance: geometry and calibration, posture recognition, control, orchestration, recording,
validation, configuration and the ``appliance`` command line."""
