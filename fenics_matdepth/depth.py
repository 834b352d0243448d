"""Placeholder."""


def material_depth(mesh):
    raise NotImplementedError
