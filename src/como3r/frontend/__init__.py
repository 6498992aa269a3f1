"""como3r.frontend"""
