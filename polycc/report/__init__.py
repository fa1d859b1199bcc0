"""Plots of covers, builds and flights (PNG, matplotlib, world frame, metres)."""
