"""CAN gateway between the car and the drift stack: DBC codec, E2E checks, arming."""
