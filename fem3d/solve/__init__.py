"""Solving: time integrators, Newton's method, Newton directions and linear solvers."""
