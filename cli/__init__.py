"""Thin click front ends over the jsgstools and jsgs libraries. No logic lives here."""
