"""labctl.tracking"""
