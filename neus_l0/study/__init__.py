"""Studies that measure one part of the method outside training (`neus-l0 study`)."""
