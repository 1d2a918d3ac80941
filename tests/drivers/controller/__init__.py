"""Tests of the controller drivers: hilcal's CAN message set, Modbus by register maps, CANopen by mapping, against
the simulated controller and peers we did not write."""
