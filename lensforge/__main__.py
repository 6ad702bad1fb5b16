"""python -m lensforge"""
from .cli import main

main()
