"""The performance suite run by `etam bench`."""
