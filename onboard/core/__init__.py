"""Pure maths core of the onboard agent.

Imports only numpy, scipy, osqp and filterpy: no sockets, clocks, loggers or globals
(enforced by the ruff `banned-api` rule in pyproject.toml).
"""
