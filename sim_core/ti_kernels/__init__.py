"""Taichi element kernels (arch cpu | cuda) of the hot elastic potentials."""
