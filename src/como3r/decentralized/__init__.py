"""como3r.decentralized"""
