"""What every part of the core stands on: settings declared once (``settings``), torch's
thread count (``threads``) and the allocator that keeps freed memory in the process
(``allocator``). Imports nothing else of the core."""
