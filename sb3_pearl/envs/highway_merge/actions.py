"""The ego's discrete actions (``Discrete(5)``): 0 accelerate, 1 decelerate, 2 cruise (IDM), 3 left, 4 right.

The names are highway-env's ``ControlledVehicle`` action names.
"""

ACCELERATE, DECELERATE, CRUISE, LANE_LEFT, LANE_RIGHT = range(5)
ACTION_NAMES = ("ACCELERATE", "DECELERATE", "CRUISE", "LANE_LEFT", "LANE_RIGHT")
