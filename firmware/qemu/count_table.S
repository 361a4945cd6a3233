/* The map table the driver fits with, linked in as bytes (COUNT_TABLE: its path, from the Makefile). */
    .section .rodata.count_table, "a"
    .balign 4
    .global count_table
count_table:
    .incbin COUNT_TABLE
    .global count_table_end
count_table_end:
