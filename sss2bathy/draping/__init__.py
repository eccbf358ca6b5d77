"""draping"""
