"""The policy seam (anything that acts in the formation env) and hand-written controllers; numpy only."""
