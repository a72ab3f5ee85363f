"""What two or more sections use: stage config base, errors, geometry, depth rendering, thread
budgets.
"""
