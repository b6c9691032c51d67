"""Calibration of a rig (`rngcam calibrate`): PSF, RS line time, GS-to-RS alignment, white balance.

Modules: `psf` (point-source frames -> PSF), `linetime` (SensorReadoutTime at several ROI
heights -> line time), `deconv` (2-D Wiener + FISTA-TV deconvolution of a diffuser image),
`align` (static pair -> GS-to-RS transform and white balance), `whitebalance` (gains for a
known transform), `targets` (what the mock cameras show), `store` (the calibration HDF5 that
capture copies into bundles), `bench` (the rig's cameras opened for calibration shots).
The algorithms take arrays; only `bench` touches cameras.
"""
