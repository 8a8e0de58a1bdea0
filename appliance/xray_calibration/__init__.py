"""X-ray calibration of the biplane system: bead phantoms, planar grids, distortion maps, MayaCam 2.0 files.

Entry points: :func:`appliance.xray_calibration.cube.calibrate_cube` (3D bead phantom, both views),
:func:`appliance.xray_calibration.grid.calibrate_grids` (planar target in several poses),
:class:`appliance.xray_calibration.distortion.GridCorrection` (image-intensifier distortion from a
perforated plate), :mod:`appliance.xray_calibration.mayacam` (XMALab/Autoscoper camera files) and
:mod:`appliance.xray_calibration.report`. The CLI is ``appliance calibrate``.
"""
