"""The bundled configuration and recordings of thinshell, found with :mod:`importlib.resources`.

``config/`` (scenes, tasks, node parameter files) and ``bags/`` (recordings: rosbag2 MCAP +
``scene.yaml``) are the repository's top-level folders; in a source checkout this package reaches
them through the links ``config`` and ``bags`` beside this file, and an installed package (pip,
``colcon build``) carries copies of them as its package data (``setup.py`` ``package_data``).
:mod:`thinshell_ros.paths` is the interface.
"""
