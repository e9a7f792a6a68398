"""labctl.sim"""
