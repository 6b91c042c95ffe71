"""The stages of the regional edit (DESIGN.md §3) as plain functions; systems call them."""
