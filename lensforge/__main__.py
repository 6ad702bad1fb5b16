"""python -m lensforge"""
from .entry import main

main()
