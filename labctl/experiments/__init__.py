"""labctl.experiments"""
