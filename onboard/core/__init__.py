"""Pure maths core of the onboard agent.

Imports only numpy, scipy, osqp and filterpy: no sockets, clocks, loggers or globals
(enforced by an import-linter contract in pyproject.toml).
"""
