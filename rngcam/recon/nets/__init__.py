"""Learned networks (RIFE HDv3 and 4.x, FFDNet) and their installed weights."""
