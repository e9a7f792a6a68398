"""labctl.library"""
