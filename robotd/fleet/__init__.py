"""Fleets: many robots of one Marvelmind map on one MQTT broker (pose, status, the signed fleet stop)."""

from robotd.fleet.hook import fleet_link
from robotd.fleet.orders import Action, Order, OrderCheck, StopHold, sign

__all__ = ["Action", "Order", "OrderCheck", "StopHold", "fleet_link", "sign"]
