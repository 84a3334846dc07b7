"""Cable-driven instrument control (SPEC section 5; dissertation chapters 4-5, appendix A)."""
