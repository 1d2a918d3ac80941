"""Measuring the machine as it is: the model each measured pose refits, where the spheres should be and how sure that
is, the search for a sphere that is not there, probe routes that keep out of the spheres' regions, and the checks that
stop a run before it moves a machine it cannot measure safely."""

from hilcal.acquisition.model import MachineBelief, PosePrediction, Priors, predict, prior_belief, refit, update
from hilcal.acquisition.routes import Ball, RouteError, plan_route
from hilcal.acquisition.spheres import BodyBelief, SpherePrediction

__all__ = ["Ball", "BodyBelief", "MachineBelief", "PosePrediction", "Priors", "RouteError", "SpherePrediction",
           "plan_route", "predict", "prior_belief", "refit", "update"]
