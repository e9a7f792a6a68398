"""labctl.vision"""
