"""labctl.runtime"""
