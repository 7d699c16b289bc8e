"""The annotation tool: tracking (ICP) and the viser browser app."""
