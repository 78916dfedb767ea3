"""GNS particle-type codes (DeepMind learning_to_simulate), the one definition
every module uses: kinematic (boundary / obstacle) 3, water 5, sand 6."""

KINEMATIC = 3
WATER = 5
SAND = 6

__all__ = ["KINEMATIC", "SAND", "WATER"]
