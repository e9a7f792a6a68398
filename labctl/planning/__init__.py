"""labctl.planning"""
