"""The stages of the regional edit (DESIGN.md §3) as plain functions and strategies; systems call them."""
