"""Readers of recorded inputs beyond the contract's image folder: ROS 1/2 bags and MCAP
files (:mod:`omnipipe.inputs.rosbag`, optional extra ``omnipipe[ros]``), and the check
for lossy (JPEG/MPEG-compressed) input (:mod:`omnipipe.inputs.lossy`).

:func:`omnipipe.dataset.open_dataset` dispatches to them (a bag's images become a
:class:`~omnipipe.dataset.Dataset` there, :func:`~omnipipe.dataset.open_bag`); video
files are read by :mod:`omnipipe.dataset` itself (OpenCV, container timestamps).
"""
