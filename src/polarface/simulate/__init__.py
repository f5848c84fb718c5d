"""polarface.simulate"""
