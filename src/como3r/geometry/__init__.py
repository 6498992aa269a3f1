"""como3r.geometry"""
