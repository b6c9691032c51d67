"""Calibration of a rig (`rngcam calibrate`): PSF, RS line time, GS-to-RS alignment, white balance.

Modules: `psf` (point-source frames -> PSF), `linetime` (SensorReadoutTime at several ROI
heights -> line time), `deconv` (2-D Wiener + FISTA-TV deconvolution of a diffuser image),
`align` (static pair -> GS-to-RS transform and white balance), `whitebalance` (gains for a
known transform), `shots` (the rig's cameras, from acquire's device factory, opened for
calibration shots), `run` (the four procedures). Results go to the calibration file
(rngcam.formats.calibration); the targets the mock cameras show are in rngcam.sim.targets.
The algorithms take arrays; only `shots` touches cameras.
"""
