"""Calibration of a real rig: camera (checkerboard views through the mirror) and laser plane.

``camera.calibrate_unified`` estimates Mei's unified model (OpenCV omnidir / Kalibr omni
convention) by bundle adjustment of checkerboard corners; ``laser.calibrate_laser`` fits
the laser plane to the laser line on the board at several poses; ``ocam_io`` reads and
writes OCamCalib's calib_results.txt. Commands: ``omnipipe calibrate camera|laser`` and
``omnipipe rig import-ocam`` (:mod:`omnipipe.calibrate.cli`).
"""
