"""labctl.records"""
