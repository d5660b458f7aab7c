"""Laser rig calibration: the beams of a laser scaler measured from images of a planar target.

:mod:`.target` finds the target and the laser spots on it in every image and turns the spots
into 3D points on the target's plane (``calibrate_images``); :mod:`.fit` tracks those points
into beams and fits each beam as a 3D line (``calibrate_rig``). The ``calibrate`` command
(:mod:`sfm_laserscale.commands.calibrate`) reads the images and writes the rig file.
"""
