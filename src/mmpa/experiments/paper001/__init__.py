"""Paper 001: reflector-enhanced AMCL, reflector dropout, SSD + IBVS tracking grasp, mobile
manipulation."""
