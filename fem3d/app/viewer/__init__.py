"""The interactive browser viewer (viser)."""
