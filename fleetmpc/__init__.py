"""fleetmpc: a quadrotor fleet holding a formation around a moving target, each vehicle with its
own Dual EKF and tube LBMPC, over MAVLink and Zenoh.

Every `fleetmpc` process (agents, SITLs, target, ground station, benchmarks) imports this
package first, so it caps OpenBLAS at one thread here, before numpy loads, unless the
environment says otherwise. The fleet's linear algebra is on matrices of a few dozen rows:
OpenBLAS's worker threads cannot speed it up, only synchronise and spin, and with a dozen fleet
processes on a few cores the spinning takes CPU from the other processes.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
