"""labctl.calibration"""
