"""uabs_rl: multi-agent 3DQN trajectory design for UAV base stations serving vehicles.

Kept free of heavy imports so that SUMO worker processes start fast.
"""

__version__ = "0.1.0"
