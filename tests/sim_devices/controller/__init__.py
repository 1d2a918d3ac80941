"""Tests of the simulated servo controller: its model, compensation, dead transducer and repeatability, and its
CANopen and Modbus personalities against peers we did not write."""
