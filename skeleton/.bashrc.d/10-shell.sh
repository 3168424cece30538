# Interactive shell comforts for a robot account (installed by fetchsync create-account).
# Files in ~/.bashrc.d/ are read in name order by interactive shells; add your own.

# A long, shared history: several terminals on one robot all append to it.
HISTCONTROL=ignoreboth
HISTSIZE=10000
HISTFILESIZE=20000
shopt -s histappend checkwinsize

# Say which robot this is: a terminal on the robot looks like one on the laptop.
if [ -z "${FETCHSYNC_PROMPT_SET:-}" ]; then
    PS1='\[\e[1;33m\]\u@\h\[\e[0m\]:\[\e[1;34m\]\w\[\e[0m\]\$ '
    FETCHSYNC_PROMPT_SET=1
fi

alias ll='ls -alF'
alias la='ls -A'
alias ..='cd ..'
alias ...='cd ../..'

# Programs installed with pip --user or by hand.
if [ -d "$HOME/.local/bin" ]; then
    case ":$PATH:" in
        *":$HOME/.local/bin:"*) ;;
        *) PATH="$HOME/.local/bin:$PATH" ;;
    esac
fi
