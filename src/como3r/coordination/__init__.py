"""como3r.coordination"""
