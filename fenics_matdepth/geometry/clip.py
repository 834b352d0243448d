"""Placeholder."""


def intersection_polygon(x_tri, x_tet):
    raise NotImplementedError
