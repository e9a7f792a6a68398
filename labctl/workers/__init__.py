"""labctl.workers"""
