"""The bundled recordings of thinshell, found with :mod:`importlib.resources`.

``bags/`` (recordings: rosbag2 MCAP + ``scene.yaml``) is the repository's top-level folder; in a
source checkout this package reaches it through the link ``bags`` beside this file, and an
installed package (pip, ``colcon build``) carries a copy of it as its package data (``setup.py``
``package_data``). The bundled configuration is :mod:`sim_core.bundled`'s;
:mod:`thinshell_ros.paths` is the interface to both.
"""
