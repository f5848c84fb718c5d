"""polarface.render"""
