"""polarface.export"""
