"""Helpers several test modules share (no tests here): tiny models, data and run utilities."""
