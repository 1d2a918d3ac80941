"""Tests of the CMM driver (I++ DME 1.4.3): against the simulated CMM on TCP and a pty, scripted peers, fuzzing."""
