"""The operator console (issue 18, docs/console.md): the IRSS primary display over the live
system and the frame control (halt, single step, resume) that ``pfma controller`` shares."""
