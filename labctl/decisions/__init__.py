"""labctl.decisions"""
