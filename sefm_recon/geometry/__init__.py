"""Geometry stages: two-view geometry, epipolar line pairs, triangulation."""
