"""como3r.evaluation"""
