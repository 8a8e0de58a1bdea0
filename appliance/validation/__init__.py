"""OTS validation sessions: the seed paper's accuracy protocol (Table 1, Fig. 4) against an optical tracker.

- :mod:`~appliance.validation.session`: the runner (robots x postures x samples) and its results;
- :mod:`~appliance.validation.fiducials`: X-ray <-> OTS registration with a fiducial phantom and a pointer;
- :mod:`~appliance.validation.reference`: the tracker's holder pose -> the robot's reference in the X-ray frame;
- :mod:`~appliance.validation.lab`: what the session asks of the lab (operator or simulated world);
- :mod:`~appliance.validation.statistics`: per-sample errors and summaries;
- :mod:`~appliance.validation.report`: Table 1 (Markdown, CSV), Fig. 4 box plots, raw samples, JSON summary.

The command is ``appliance validate`` (``appliance/commands/validate.py``).
"""
