"""The CiA 402 servo drive emulated: plant, object dictionary, CAN node."""
