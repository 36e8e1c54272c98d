"""What a person reads: figures (the only place matplotlib is imported), file writers of every step's
results, and the campaign report.
"""
